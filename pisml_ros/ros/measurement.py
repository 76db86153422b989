"""measurement node: publishes dq measurements as MeasurementBatch on /pisml/measurement.

Sources: ``sim`` (the virtual HIL running a scenario of the paper's protocol,
with optional effects and noise), ``csv`` or ``bag`` (a recorded dataset).
Batches (``batch_size`` samples each) are paced at ``rate`` × real time
(0 = as fast as the subscribers take them).
"""
from __future__ import annotations

import itertools
import time

from .common import MEASUREMENT_TOPIC, declare, measurement_qos, publish_diagnostics, run_node, status

import rclpy  # noqa: E402  (common set up the DDS environment first)
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from pisml_msgs.msg import MeasurementBatch  # noqa: E402
from rclpy.node import Node  # noqa: E402

from ..data import read_dataset  # noqa: E402
from ..data.bag_io import dataset_to_batches  # noqa: E402
from .conversions import batch_message  # noqa: E402


def load_source(source: str, path: str, scenario: str, seed: int, snr_db: float, params_file: str,
                effects: list[str], effect_params: list[str], noisy_inputs: bool = False):
    """The dataset a measurement source plays (core calls only; ``noisy_inputs``: sim's noise on
    the grid inputs too, as ``pisml simulate --noisy-inputs``)."""
    if source in ("csv", "bag"):
        if not path:
            raise ValueError(f"parameter path: required for source={source}")
        return read_dataset(path)
    if source == "sim":
        from ..plant import InverterPlant, PlantParameters, load_parameters
        from ..plant.effects import parse_effect_assignments
        from ..plant.noise import add_measurement_noise
        from ..plant.scenarios import generate, schedules_for

        params = load_parameters(params_file) if params_file else PlantParameters()
        plant = InverterPlant(params, parse_effect_assignments([e for e in effects if e], [a for a in effect_params if a]))
        schedules, duration = schedules_for(scenario, seed=seed)
        # (settings the plant cannot simulate raise ParameterError, a ValueError: a configuration error)
        dataset = generate(plant, schedules, duration, metadata={"scenario": scenario, "seed": seed})
        if snr_db > 0:
            return add_measurement_noise(dataset, snr_db, seed=seed + 1_000_003, include_inputs=noisy_inputs)
        if noisy_inputs:
            raise ValueError("parameter noisy_inputs: needs snr_db > 0 (the noise level)")
        return dataset
    raise ValueError(f"parameter source: {source!r} is not one of sim, csv, bag")


class MeasurementNode(Node):
    def __init__(self):
        super().__init__("measurement")
        self.source = declare(self, "source", "sim", "where samples come from: sim | csv | bag")
        path = declare(self, "path", "", "CSV file or bag directory for source=csv|bag")
        scenario = declare(self, "scenario", "train", "sim: scenario of the paper protocol: train | test | smallsignal")
        seed = declare(self, "seed", 0, "sim: random seed of the scenario and noise", 0, 2**31 - 1)
        snr_db = declare(self, "snr_db", 0.0, "sim: measurement SNR in dB (0 = clean)", 0.0, 200.0)
        noisy_inputs = declare(self, "noisy_inputs", False, "sim: the noise on the grid inputs (ug, theta_g) too, "
                                                            "not on the states only")
        params_file = declare(self, "params_file", "", "sim: plant parameter YAML/JSON (empty = nameplate)")
        effects = declare(self, "effects", [""], "sim: named effects to switch on (pisml effects lists them)")
        effect_params = declare(self, "effect_params", [""], "sim: effect parameters as NAME.KEY=VALUE")
        self.rate = declare(self, "rate", 1.0, "playback speed, x real time (0 = as fast as possible)", 0.0, 1000.0)
        self.batch_size = declare(self, "batch_size", 100, "samples per MeasurementBatch", 1, 10000)
        self.loop = declare(self, "loop", False, "start again when the data is exhausted")
        self.exit_when_done = declare(self, "exit_when_done", False, "shut the node down after the last batch")
        self.wait_for_subscribers = declare(
            self, "wait_for_subscribers", 1, "hold the first batch until this many subscribers are matched "
            "(reliable delivery starts at the match; 0 = don't wait)", 0, 1000)
        self.start_delay = declare(self, "start_delay", 0.5, "seconds to wait after that before the first batch",
                                   0.0, 60.0)
        depth = declare(self, "qos_depth", 5000, "depth of the reliable measurement queue", 10, 1000000)

        self.dataset = load_source(self.source, path, scenario, seed, snr_db, params_file, effects, effect_params,
                                   noisy_inputs)
        self.publisher = self.create_publisher(MeasurementBatch, MEASUREMENT_TOPIC, measurement_qos(depth))
        self.diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.batches = list(dataset_to_batches(self.dataset, self.batch_size))
        # sample time at which each batch is due, batches laid end to end
        sizes = [stop - start for _, start, stop, _ in self.batches]
        self.batch_time = [self.dataset.dt * n for n in itertools.accumulate([0] + sizes[:-1])]
        self.pass_time = self.dataset.dt * sum(sizes)  # data time of one pass
        self.next_batch = 0
        self.published_samples = 0
        self.passes = 0
        self.t_start = None
        self.timer = self.create_timer(0.002, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            f"source={self.source}: {len(self.dataset)} trajectories, {self.dataset.n_samples} samples, "
            f"{len(self.batches)} batches at {self.rate:g}x real time")

    def _due(self) -> int:
        """Index one past the last batch whose time has come."""
        if self.rate <= 0:
            return min(self.next_batch + 20, len(self.batches))
        elapsed = (time.monotonic() - self.t_start) * self.rate
        due = self.next_batch
        while due < len(self.batches) and self.batch_time[due] <= elapsed + 1e-12:
            due += 1
        return due

    def _tick(self):
        now = time.monotonic()
        if self.t_start is None:
            if self.passes == 0 and self.publisher.get_subscription_count() < self.wait_for_subscribers:
                return
            self.t_start = now + (self.start_delay if self.passes == 0 else 0.0)
        if now < self.t_start:
            return
        stamp = self.get_clock().now().to_msg()
        for k in range(self.next_batch, self._due()):
            traj, start, stop, last = self.batches[k]
            self.publisher.publish(batch_message(traj, start, stop, last, self.dataset.dt, self.dataset.state_names,
                                                 self.dataset.input_names, stamp))
            self.published_samples += stop - start
            self.next_batch = k + 1
        if self.next_batch >= len(self.batches):
            self.passes += 1
            if self.loop:
                # the next pass is due where this one's data ends, not when this tick happens to
                # run: a pass that fell behind (timer late under load) keeps catching up
                self.next_batch = 0
                if self.rate > 0:
                    self.t_start += self.pass_time / self.rate
                return
            self.timer.cancel()
            self.get_logger().info(f"done: published {self.published_samples} samples")
            self._publish_diagnostics()
            if self.exit_when_done:
                self.create_timer(0.2, self._shutdown_when_acked)

    def _shutdown_when_acked(self):
        # reliable delivery of the tail: Fast DDS may take seconds to resend what a reader missed,
        # so wait for every matched reader to acknowledge before shutting down (bounded)
        from rclpy.duration import Duration

        if self.publisher.get_subscription_count() and not self.publisher.wait_for_all_acked(Duration(seconds=30)):
            self.get_logger().warning("not every subscriber acknowledged the last batches within 30 s")
        rclpy.try_shutdown()

    def _publish_diagnostics(self):
        publish_diagnostics(self, self.diagnostics, [status(
            "pisml: measurement", DiagnosticStatus.OK,
            "publishing" if self.next_batch < len(self.batches) else "done",
            {"published_samples": self.published_samples, "batches": f"{self.next_batch}/{len(self.batches)}",
             "passes": self.passes}, hardware_id=self.source)])


def main(args=None) -> int:
    return run_node(MeasurementNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
