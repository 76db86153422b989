"""Shared plumbing of the nodes: loopback DDS, QoS profiles, parameter declaration, main loop."""
from __future__ import annotations

import faulthandler
import signal
import sys

from .dds_env import configure_loopback_dds

configure_loopback_dds()  # before rclpy is imported anywhere in this process

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

MEASUREMENT_TOPIC = "/pisml/measurement"
MODEL_TOPIC = "/pisml/model"
STABILITY_TOPIC = "/pisml/stability"


def measurement_qos(depth: int = 5000) -> QoSProfile:
    """Reliable with a deep queue: identification must not lose samples."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def latched_qos(depth: int = 1) -> QoSProfile:
    """Transient-local (default depth 1): a late subscriber still gets the latest model or report(s)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def declare(node, name: str, default, description: str, low=None, high=None, read_only: bool = False):
    """Declare a parameter with a description and, for numbers, a range; return its value."""
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    if low is not None and high is not None:
        if isinstance(default, bool):
            pass
        elif isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high), step=0)]
        elif isinstance(default, float):
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high),
                                                                  step=0.0)]
    return node.declare_parameter(name, default, descriptor).value


def status(name: str, level, message: str, values: dict | None = None, hardware_id: str = "pisml"):
    """A DiagnosticStatus with key/value pairs (values shown as strings)."""
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

    level = DiagnosticStatus.OK if level is None else level
    out = DiagnosticStatus(level=level, name=name, hardware_id=hardware_id, message=message)
    out.values = [KeyValue(key=str(k), value=str(v)) for k, v in (values or {}).items()]
    return out


def publish_diagnostics(node, publisher, statuses) -> None:
    """Publish a DiagnosticArray of ``statuses`` stamped with the node's clock."""
    from diagnostic_msgs.msg import DiagnosticArray

    msg = DiagnosticArray(status=list(statuses))
    msg.header.stamp = node.get_clock().now().to_msg()
    publisher.publish(msg)


def run_node(node_class, args=None) -> int:
    """Init rclpy (``--ros-args`` honoured), spin the node on a multi-threaded executor,
    shut down cleanly on SIGINT/SIGTERM; exit status 0, or 2 on a configuration error.

    ``kill -USR1 PID`` prints every thread's Python stack to stderr (a node that will not stop).
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

    faulthandler.register(signal.SIGUSR1, all_threads=True)
    rclpy.init(args=sys.argv if args is None else args)
    node = None
    executor = None
    status = 0
    try:
        node = node_class()
        executor = MultiThreadedExecutor(num_threads=4)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as err:  # bad parameter values: one line, no traceback
        print(f"{node_class.__name__}: configuration error: {err}", file=sys.stderr)
        status = 2
    finally:
        if node is not None:
            node.destroy_node()
        if executor is not None:
            # wakes the pool's idle threads. A Ctrl-C that lands while the pool starts a thread
            # (inside Thread.start) leaves that thread unknown to the interpreter's exit hook,
            # and the process would wait for it forever (2 of 106 stops hung in a looped node test)
            executor.shutdown(timeout_sec=1.0, wait_for_threads=False)
        rclpy.try_shutdown()
    return status
