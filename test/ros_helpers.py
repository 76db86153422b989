"""Helpers of the topic-level tests: start real node processes, spin a probe node until a condition."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.executable).parent


def start_node(executable: str, *ros_args: str, log_dir: Path) -> subprocess.Popen:
    """Start a node's console script as its own process (same DDS domain and loopback profile)."""
    log = open(log_dir / f"{executable}.log", "w")
    cmd = [str(BIN / executable)]
    if ros_args:
        cmd += ["--ros-args", *ros_args]
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ))
    proc.log_path = log_dir / f"{executable}.log"
    return proc


def stop_node(proc: subprocess.Popen, timeout: float = 10.0) -> int:
    """SIGINT, then wait; returns the exit status (-9: killed after the timeout, its threads' stacks
    in its log and on stdout, which pytest shows with the failure)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGUSR1)  # nodes dump their stacks (run_node's faulthandler)
            time.sleep(1.0)
            log = getattr(proc, "log_path", None)
            print(f"pid {proc.pid} did not stop within {timeout} s"
                  + (f"; its log:\n{log.read_text()}" if log is not None else ""))
            proc.kill()
            proc.wait()
            return -9
    return proc.returncode


def spin_until(node, condition, timeout: float, executor=None) -> bool:
    """Spin ``node`` until ``condition()`` is true or ``timeout`` seconds pass."""
    import rclpy

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if executor is not None:
            executor.spin_once(timeout_sec=0.05)
        else:
            rclpy.spin_once(node, timeout_sec=0.05)
        if condition():
            return True
    return False


def start_cli(name: str, *args: str, log_dir: Path) -> subprocess.Popen:
    """Start ``pisml ARGS`` (python -m pisml_ros.cli) as its own process; output in ``log_dir/name.log``."""
    log = open(log_dir / f"{name}.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "pisml_ros.cli", *map(str, args)], stdout=log,
                            stderr=subprocess.STDOUT, env=dict(os.environ))
    proc.log_path = log_dir / f"{name}.log"
    return proc


def wait_for_log(proc: subprocess.Popen, text: str, timeout: float) -> bool:
    """Wait until ``text`` appears in the process's log (False on timeout or when it exits first)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if text in proc.log_path.read_text():
            return True
        if proc.poll() is not None:
            return text in proc.log_path.read_text()
        time.sleep(0.1)
    return False


def diagnostic_values(msgs, name):
    """The latest DiagnosticStatus called ``name`` in a list of DiagnosticArray, and its values as a dict."""
    for msg in reversed(msgs):
        for status in msg.status:
            if status.name == name:
                return status, {kv.key: kv.value for kv in status.values}
    return None, {}


def wait_future(node, future, timeout: float):
    """Spin ``node`` until ``future`` is done; its result (AssertionError on timeout)."""
    if not spin_until(node, future.done, timeout):
        raise AssertionError(f"no answer within {timeout} s")
    return future.result()


def stop_all(*procs) -> list:
    """Stop every process (None entries skipped) before anything is asserted; their exit statuses."""
    return [stop_node(p) for p in procs if p is not None]


def probe_node(name: str):
    """A plain rclpy node for a test module to subscribe with (generator for a module-scoped fixture)."""
    import rclpy

    rclpy.init()
    node = rclpy.create_node(name)
    yield node
    node.destroy_node()
    rclpy.shutdown()
