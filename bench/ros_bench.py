"""Benchmark of the live graph: link throughput/latency, model stage times, memory.

    python bench/ros_bench.py [--seconds 60] [--out bench/ros_results.json]

Starts the measurement node (virtual HIL, training scenario at 40 dB, looped, paced in real
time: 10 kHz of 13 states + 2 inputs), the identifier (PISML, retraining on new data, so it
trains while the link runs) and the analyser as separate processes on loopback DDS. A probe
subscriber in this process counts every sample and its latency (header stamp → arrival), checks
that each trajectory's samples arrive without gaps, and times the stages: 12th trajectory
complete → backbone / hybrid / explicit model on /pisml/model → StabilityReport. Node memory
(VmRSS) is sampled every second; for the identifier also with its child processes (the training
process of the current run and the warm one for the next), as ``identifier+children``. Prints the figures and writes them to the results JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pisml_ros.ros.dds_env import configure_loopback_dds

BENCH = Path(__file__).resolve().parent


def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def children(pid: int) -> list[int]:
    """Direct child processes of ``pid`` (the identifier's training process)."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry.name))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="length of the link test (s of real time)")
    parser.add_argument("--out", default=str(BENCH / "ros_results.json"))
    args = parser.parse_args(argv)
    configure_loopback_dds()
    os.environ.setdefault("ROS_DOMAIN_ID", str(50 + os.getpid() % 50))
    import rclpy
    from pisml_msgs.msg import IdentifiedModel, MeasurementBatch, StabilityReport

    from pisml_ros.ros.conversions import message_metrics
    from pisml_ros.ros.common import MEASUREMENT_TOPIC, MODEL_TOPIC, latched_qos, measurement_qos

    work = Path(tempfile.mkdtemp(prefix="pisml_ros_bench_"))
    params = work / "params.yaml"
    params.write_text(f"""
measurement:
  ros__parameters: {{source: sim, scenario: train, snr_db: 40.0, seed: 0, rate: 1.0, loop: true,
                     wait_for_subscribers: 2, start_delay: 1.0}}
identifier:
  ros__parameters: {{method: pisml, min_trajectories: 12, retrain_policy: on_new_data,
                     retrain_min_new_trajectories: 12, max_train_trajectories: 24, output_dir: "{work / 'identifier'}",
                     smallsignal_path: "{BENCH.parent / 'bags' / 'smallsignal_40dB'}"}}
analyser:
  ros__parameters: {{ug_points: [0.8, 1.0]}}  # default sweep: 23 points of ug for the margins
""")
    procs = {}
    for name in ("analyser", "identifier", "measurement"):
        procs[name] = subprocess.Popen([sys.executable, "-m", f"pisml_ros.ros.{name}", "--ros-args",
                                        "--params-file", str(params)], stdout=open(work / f"{name}.log", "w"),
                                       stderr=subprocess.STDOUT)
    rclpy.init()
    node = rclpy.create_node("pisml_ros_bench_probe")
    samples = [0]
    latencies = []
    last_index: dict = {}
    gaps = [0]
    ended = []
    ends = []  # (arrival, samples received so far) at each trajectory end: the steady delivery rate
    events: dict = {}
    t0 = time.monotonic()

    def on_batch(msg):
        now = node.get_clock().now().nanoseconds
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        latencies.append((now - stamp) / 1e6)
        n = len(msg.x) // max(len(msg.state_names), 1)
        samples[0] += n
        key = int(msg.trajectory_id)
        first = int(msg.first_sample_index)
        expected = last_index.get(key)
        if expected is not None and first not in (expected, 0):  # 0: the looped scenario starts again
            gaps[0] += 1
        last_index[key] = first + n
        if msg.end_of_trajectory:
            ended.append(time.monotonic())
            ends.append((ended[-1], samples[0]))
            if len(ended) == 12:
                events["12th_trajectory"] = time.monotonic()

    reports: list = []  # (arrival, model_id): the stages of one run share its model_id

    def on_model(msg):
        # the first explicit model of a run is the best one before refinement; the final one closes it
        keys = [f"model_{msg.stage}"] + (["model_final"] if message_metrics(msg).get("final") == 1.0 else [])
        for key in keys:
            events.setdefault(key, time.monotonic())
            events.setdefault(f"{key}_id", msg.model_id)

    def on_report(msg):
        reports.append((time.monotonic(), msg.model_id))

    def report_after(stage):
        """Seconds from the stage's model to the first report on that model arriving after it."""
        t_model, model_id = events.get(f"model_{stage}"), events.get(f"model_{stage}_id")
        later = [t for t, mid in reports if mid == model_id and t_model is not None and t >= t_model]
        return round(min(later) - t_model, 3) if later else None

    node.create_subscription(MeasurementBatch, MEASUREMENT_TOPIC, on_batch, measurement_qos(5000))
    node.create_subscription(IdentifiedModel, MODEL_TOPIC, on_model, latched_qos())
    node.create_subscription(StabilityReport, "/pisml/stability", on_report, latched_qos(8))
    memory = {name: [] for name in procs}
    link_start = None
    deadline = time.monotonic() + args.seconds + 600
    next_sample = 0.0
    try:
        while time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
            now = time.monotonic()
            if samples[0] and link_start is None:
                link_start = now
            if now >= next_sample:
                for name, proc in procs.items():
                    memory[name].append((now - t0, rss_mb(proc.pid)))
                    if name == "identifier":
                        memory.setdefault("identifier+children", []).append(
                            (now - t0, rss_mb(proc.pid) + float(np.nansum([rss_mb(c) for c in children(proc.pid)]))))
                next_sample = now + 1.0
            if any(p.poll() is not None for p in procs.values()):
                raise SystemExit(f"a node exited early; logs in {work}")
            if link_start and now - link_start >= args.seconds and report_after("final") is not None:
                break
    finally:
        for proc in procs.values():
            proc.terminate()
        for proc in procs.values():
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
        node.destroy_node()
        rclpy.shutdown()
    link_seconds = time.monotonic() - link_start if link_start else 0.0
    # the measurement node's own count, from its log ("published N samples" is logged per pass)
    lat = np.array(latencies)
    twelfth = events.get("12th_trajectory")

    def after(key):
        return round(events[key] - twelfth, 3) if key in events and twelfth else None

    result = {
        "command": "python bench/ros_bench.py" + (f" --seconds {args.seconds:g}" if args.seconds != 60 else ""),
        "date": time.strftime("%Y-%m-%d"), "machine": f"{os.cpu_count()} cores",
        "link": {"seconds": round(link_seconds, 1), "samples_received": samples[0],
                 "samples_per_second": round(samples[0] / link_seconds, 1) if link_seconds else None,
                 # first to last trajectory end: the paced rate, without the start-up and the wait at the end
                 "samples_per_second_steady": round((ends[-1][1] - ends[0][1]) / (ends[-1][0] - ends[0][0]), 1)
                 if len(ends) > 1 else None,
                 "batches": len(latencies), "index_gaps": gaps[0],
                 "latency_ms": {f"p{q}": round(float(np.percentile(lat, q)), 3) for q in (50, 90, 99, 100)}
                 if lat.size else None},
        "stages_after_12th_trajectory_s": {stage: after(f"model_{stage}")
                                           for stage in ("backbone", "hybrid", "explicit", "final")},
        "report_after_model_s": {stage: report_after(stage) for stage in ("backbone", "explicit", "final")},
        "memory_mb": {name: {"start": round(v[min(5, len(v) - 1)][1], 1), "end": round(v[-1][1], 1),
                             "max": round(max(m for _, m in v), 1),
                             "every_30_s": [round(m, 1) for _, m in v[::30]]} for name, v in memory.items() if v},
        # the identifier logs every batch it rejects (overlaps, gaps it cannot place): losses on its side
        "identifier_rejected_batches": sum("rejected" in line for line in
                                           (work / "identifier.log").read_text(errors="replace").splitlines()),
        "identifier_runs": [line.split("]: ", 1)[-1] for line in
                            (work / "identifier.log").read_text(errors="replace").splitlines() if " done in " in line],
        "logs": str(work),
    }
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
