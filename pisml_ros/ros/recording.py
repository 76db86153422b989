"""Record live topics to a rosbag2 (mcap) and play one back, without the ros2 CLI.

``record`` subscribes to the chosen topics in their serialized form (the CDR
bytes go into the bag as received, so any message type works) and writes them
with ``rosbags``; the bag appears atomically when recording ends (duration
reached, SIGINT or SIGTERM). Each topic is recorded with a QoS compatible with
its publishers (reliable/transient-local where they all are), and those QoS
profiles are stored in the bag's metadata, as ``ros2 bag record`` does.

``play`` publishes every message of a bag (or of some topics) as raw bytes,
paced by the bag's log times (× ``rate``; 0 = as fast as possible), optionally
in a loop; topics recorded transient-local are republished transient-local.
Bags written here play in ``ros2 bag play`` and the other way round.
"""
from __future__ import annotations

import importlib
import shutil
import signal
import sys
import time
from pathlib import Path

from .common import MEASUREMENT_TOPIC, MODEL_TOPIC, STABILITY_TOPIC, latched_qos, measurement_qos

import rclpy  # noqa: E402  (common set up the loopback DDS environment first)
from rclpy.duration import Duration  # noqa: E402
from rclpy.executors import ExternalShutdownException  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

from ..data import DataError  # noqa: E402
from ..data.bag_io import find_msg_definition  # noqa: E402

#: types of the project's topics, so they can be recorded before anyone publishes them
KNOWN_TYPES = {
    MEASUREMENT_TOPIC: "pisml_msgs/msg/MeasurementBatch",
    MODEL_TOPIC: "pisml_msgs/msg/IdentifiedModel",
    STABILITY_TOPIC: "pisml_msgs/msg/StabilityReport",
    "/pisml/gap": "pisml_msgs/msg/GapReport",
    "/pisml/root_locus": "std_msgs/msg/String",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}
LATCHED_TOPICS = (MODEL_TOPIC, STABILITY_TOPIC, "/pisml/gap", "/pisml/root_locus")


def full_typestore():
    """rosbags Kilted type store with every pisml_msgs message registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_KILTED)
    types = {}
    for path in sorted(find_msg_definition().parent.glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"pisml_msgs/msg/{path.stem}"))
    store.register(types)
    return store


def message_class(type_name: str):
    """The rclpy message class of ``pkg/msg/Name``."""
    try:
        pkg, kind, name = type_name.split("/")
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (ValueError, ImportError, AttributeError):
        raise DataError(f"message type {type_name!r} is not available in this Python environment") from None


def _qos_for(topic: str, publishers=()) -> QoSProfile:
    """A subscription QoS that matches ``publishers`` (endpoint infos); defaults by topic."""
    if topic == MEASUREMENT_TOPIC:
        qos = measurement_qos()
    elif topic in LATCHED_TOPICS:
        qos = latched_qos(depth=100)
    else:
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
    if publishers:
        if any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in publishers):
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        if all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers):
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
        else:
            qos.durability = DurabilityPolicy.VOLATILE
    return qos


def _bag_qos(qos: QoSProfile):
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    never = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=int(qos.depth),
               reliability=QosReliability.BEST_EFFORT if qos.reliability == ReliabilityPolicy.BEST_EFFORT
               else QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL if qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
               else QosDurability.VOLATILE,
               deadline=never, lifespan=never, liveliness=QosLiveliness.AUTOMATIC,
               liveliness_lease_duration=never, avoid_ros_namespace_conventions=False)


class Recorder:
    """Subscribe to ``topics`` on ``node`` and write what arrives into a bag being built.

    Call :meth:`poll` regularly (it subscribes to topics as their types become known),
    spin the node, then :meth:`close` to finish the bag at ``out``.
    """

    def __init__(self, node, topics, out: str | Path, storage: str = "mcap", log=print):
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.node, self.out, self.log = node, Path(out), log
        self.topics = [t if t.startswith("/") else "/" + t for t in topics]
        if not self.topics:
            raise ValueError("no topics to record")
        plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
        if plugin is None:
            raise ValueError(f"unknown bag storage {storage!r}; use mcap or sqlite3")
        if self.out.exists():
            raise ValueError(f"{self.out}: exists (choose a new directory)")
        self.store = full_typestore()
        self.staging = self.out.parent / f".{self.out.name}.partial"
        shutil.rmtree(self.staging, ignore_errors=True)
        self.staging.mkdir(parents=True)
        self.writer = Writer(self.staging / self.out.name, version=9, storage_plugin=plugin)
        self.writer.open()
        self.subscriptions = {}
        self.counts = {t: 0 for t in self.topics}
        self.closed = False

    def poll(self):
        """Subscribe to the topics whose type is now known (from the graph or :data:`KNOWN_TYPES`)."""
        graph = dict(self.node.get_topic_names_and_types())
        for topic in self.topics:
            if topic in self.subscriptions:
                continue
            types = graph.get(topic) or ([KNOWN_TYPES[topic]] if topic in KNOWN_TYPES else [])
            if not types:
                continue
            type_name = types[0]
            publishers = self.node.get_publishers_info_by_topic(topic)
            if topic not in KNOWN_TYPES and not publishers:
                continue
            qos = _qos_for(topic, publishers)
            if type_name not in self.store.types:
                raise DataError(f"{topic}: type {type_name} is unknown to the bag writer")
            conn = self.writer.add_connection(topic, type_name, typestore=self.store,
                                              offered_qos_profiles=[_bag_qos(qos)])

            def on_message(raw, conn=conn, topic=topic):
                if not self.closed:
                    self.writer.write(conn, time.time_ns(), raw)
                    self.counts[topic] += 1

            self.subscriptions[topic] = self.node.create_subscription(message_class(type_name), topic, on_message,
                                                                      qos, raw=True)
            self.log(f"recording {topic} [{type_name}]")

    def missing(self) -> list[str]:
        return [t for t in self.topics if t not in self.subscriptions]

    def close(self) -> Path:
        """Finish the bag and move it to ``out``."""
        if self.closed:
            return self.out
        self.closed = True
        for sub in self.subscriptions.values():
            self.node.destroy_subscription(sub)
        self.writer.close()
        (self.staging / self.out.name).rename(self.out)
        self.staging.rmdir()
        return self.out


def record(topics, out, duration: float | None = None, storage: str = "mcap", log=print) -> dict:
    """Record ``topics`` from the live graph into the bag ``out`` until ``duration`` seconds
    pass (None: until SIGINT/SIGTERM). Returns the message count per topic."""
    if duration is not None and not duration > 0:
        raise ValueError(f"duration must be > 0 s, got {duration}")
    rclpy.init(args=[sys.argv[0]], signal_handler_options=SignalHandlerOptions.NO)  # SIGINT/SIGTERM: ours
    node = rclpy.create_node("pisml_recorder")
    recorder = None
    old_term = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        recorder = Recorder(node, topics, out, storage, log)
        deadline = None if duration is None else time.monotonic() + duration
        next_poll = 0.0
        try:
            while rclpy.ok() and (deadline is None or time.monotonic() < deadline):
                if time.monotonic() >= next_poll:
                    recorder.poll()
                    next_poll = time.monotonic() + 0.5
                rclpy.spin_once(node, timeout_sec=0.05)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        _drain(node, recorder)
        if recorder.missing():
            log(f"never saw a publisher of {recorder.missing()} (not recorded)")
        recorder.close()
        return dict(recorder.counts)
    except BaseException:
        if recorder is not None and not recorder.closed:
            recorder.closed = True
            shutil.rmtree(recorder.staging, ignore_errors=True)
        raise
    finally:
        signal.signal(signal.SIGTERM, old_term)
        node.destroy_node()
        rclpy.try_shutdown()


def _drain(node, recorder, idle: float = 0.5, limit: float = 5.0) -> None:
    """Write the messages that already reached this process before the bag closes: a stop ends the
    listening, not the delivery of what waits in the subscriptions' queues (a recorder starved of
    CPU by a training beside it lags behind the graph), nor the repair of a lost sample, which
    comes with the writer's next heartbeat (100 ms in config/fastdds_loopback.xml). Until ``idle``
    seconds bring nothing, at most ``limit`` seconds; a second Ctrl-C ends it."""
    if not rclpy.ok():
        return
    deadline = time.monotonic() + limit
    try:
        while time.monotonic() < deadline:
            before = sum(recorder.counts.values())
            rclpy.spin_once(node, timeout_sec=idle)
            if sum(recorder.counts.values()) == before:
                return
    except (KeyboardInterrupt, ExternalShutdownException):
        pass


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def _publisher_qos(topic: str, conn) -> QoSProfile:
    profiles = list(getattr(conn.ext, "offered_qos_profiles", None) or [])
    qos = _qos_for(topic)
    if profiles:
        from rosbags.interfaces import QosDurability, QosReliability

        if all(p.durability == QosDurability.TRANSIENT_LOCAL for p in profiles):
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
        if any(p.reliability == QosReliability.BEST_EFFORT for p in profiles):
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
    if qos.durability == DurabilityPolicy.TRANSIENT_LOCAL:
        qos.depth = max(qos.depth, 100)
    return qos


def play(bag, rate: float = 1.0, loop: bool = False, topics=None, wait_for_subscribers: int = 1,
         wait_timeout: float = 30.0, log=print) -> int:
    """Publish the messages of ``bag`` paced by their log times × ``rate`` (0 = as fast as possible).

    Waits (up to ``wait_timeout`` s) until ``wait_for_subscribers`` subscribers are matched on the
    measurement topic (or on the first topic when the bag has none). Returns the number published.
    """
    from rosbags.rosbag2 import Reader

    if not rate >= 0:
        raise ValueError(f"rate must be >= 0, got {rate}")
    bag = Path(bag)
    if not (bag / "metadata.yaml").is_file():
        raise DataError(f"{bag}: not a rosbag2 directory (no metadata.yaml)")
    try:
        reader = Reader(bag)
        reader.open()
    except Exception as err:  # rosbags raises several types for corrupt bags
        raise DataError(f"{bag}: cannot open bag: {err}") from None
    rclpy.init(args=[sys.argv[0]], signal_handler_options=SignalHandlerOptions.NO)  # SIGINT/SIGTERM: ours
    node = rclpy.create_node("pisml_player")
    old_term = signal.signal(signal.SIGTERM, _raise_interrupt)
    published = 0
    try:
        wanted = None if not topics else {t if t.startswith("/") else "/" + t for t in topics}
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        if not conns:
            raise DataError(f"{bag}: no messages on {sorted(wanted) if wanted else 'any topic'} "
                            f"(topics: {sorted({c.topic for c in reader.connections})})")
        publishers = {}
        for conn in conns:
            if conn.topic not in publishers:
                publishers[conn.topic] = node.create_publisher(message_class(conn.msgtype), conn.topic,
                                                               _publisher_qos(conn.topic, conn))
        gate = publishers.get(MEASUREMENT_TOPIC) or next(iter(publishers.values()))
        deadline = time.monotonic() + wait_timeout
        while gate.get_subscription_count() < wait_for_subscribers:
            if time.monotonic() > deadline:
                raise DataError(f"no {wait_for_subscribers} subscriber(s) on {gate.topic_name} within "
                                f"{wait_timeout:g} s")
            time.sleep(0.05)
        if wait_for_subscribers:
            time.sleep(0.5)  # reliable delivery starts once the match is complete on both sides
        log(f"playing {bag} ({', '.join(sorted(publishers))}) at "
            f"{'full speed' if rate == 0 else f'{rate:g}x'}{', looping' if loop else ''}")
        while True:
            start_wall, start_log = time.monotonic(), None
            for conn, stamp, raw in reader.messages(connections=conns):
                if start_log is None:
                    start_log = stamp
                if rate > 0:
                    delay = start_wall + (stamp - start_log) * 1e-9 / rate - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                publishers[conn.topic].publish(bytes(raw))
                published += 1
            if not loop:
                break
        # reliable delivery of the tail: wait until every matched subscriber acknowledged it
        acked_start = time.monotonic()
        for publisher in publishers.values():
            if publisher.get_subscription_count() and not publisher.wait_for_all_acked(Duration(seconds=30)):
                log(f"{publisher.topic_name}: not every subscriber acknowledged the last messages within 30 s")
        if time.monotonic() - acked_start > 1.0:
            log(f"all messages acknowledged after {time.monotonic() - acked_start:.1f} s")
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, old_term)
        reader.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return published
