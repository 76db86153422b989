"""gap node: runs the gap workflow on measurements arriving on /pisml/measurement.

Buffers complete trajectories; once ``min_trajectories`` have arrived (and again
after every ``rerun_every`` new ones) it compares them with the configured
reference (the virtual HIL with nameplate ``params_file``, or an explicit
``model_path``) in a background thread, and publishes ``pisml_msgs/GapReport`` on
``/pisml/gap`` (transient-local). The executor never blocks.
"""
from __future__ import annotations

import threading

from .common import MEASUREMENT_TOPIC, declare, latched_qos, measurement_qos, publish_diagnostics, run_node, status

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from pisml_msgs.msg import GapReport, MeasurementBatch  # noqa: E402
from rclpy.node import Node  # noqa: E402

from ..data import DataError, validate_batch  # noqa: E402
from ..data.stream import TrajectoryBuffer  # noqa: E402
from .conversions import gap_message  # noqa: E402

GAP_TOPIC = "/pisml/gap"


class GapNode(Node):
    def __init__(self):
        super().__init__("gap")
        params_file = declare(self, "params_file", "", "reference: virtual HIL nameplate YAML/JSON (empty = defaults)")
        model_path = declare(self, "model_path", "", "reference: explicit model JSON (overrides params_file)")
        self.min_trajectories = declare(self, "min_trajectories", 2, "trajectories before the first run", 1, 10000)
        self.rerun_every = declare(self, "rerun_every", 0, "re-run after this many new trajectories (0 = once)",
                                   0, 10000)
        self.max_effects = declare(self, "max_effects", 3, "effects to name at most", 0, 10)
        self.output_dir = declare(self, "output_dir", "", "also write report.json/gap.png here (empty = no files)")
        self.reference, self.reference_name = self._load_reference(params_file, model_path)
        self.buffer = TrajectoryBuffer()
        self.rejected = 0
        self.last_error = ""
        self.state = "waiting"
        self.last_run_count = 0
        self.worker = None
        self.lock = threading.Lock()
        self.create_subscription(MeasurementBatch, MEASUREMENT_TOPIC, self._on_batch, measurement_qos())
        self.publisher = self.create_publisher(GapReport, GAP_TOPIC, latched_qos())
        self.diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(1.0, self._publish_diagnostics)

    def _load_reference(self, params_file, model_path):
        from ..gap import ModelReference, PlantReference
        from ..model import ExplicitModel
        from ..plant import PlantParameters, load_parameters

        if model_path:
            return ModelReference(ExplicitModel.load(model_path)), f"model:{model_path}"
        params = load_parameters(params_file) if params_file else PlantParameters()
        return PlantReference(params), f"plant:{params_file or 'nameplate'}"

    def _on_batch(self, msg):
        try:
            arrays = validate_batch(msg, where="batch")
            with self.lock:
                self.buffer.add(int(msg.trajectory_id), int(msg.first_sample_index), float(msg.t0), arrays,
                                bool(msg.end_of_trajectory))
        except DataError as err:
            self.rejected += 1
            self.last_error = str(err)
            self.get_logger().warning(f"rejected {err}")
            return
        self._maybe_run()

    def _maybe_run(self):
        count = len(self.buffer.complete)
        due = count >= self.min_trajectories and (
            self.last_run_count == 0 or (self.rerun_every and count - self.last_run_count >= self.rerun_every))
        if not due or (self.worker is not None and self.worker.is_alive()):
            return
        with self.lock:
            data = self.buffer.dataset()
        self.last_run_count = count
        self.worker = threading.Thread(target=self._run, args=(data,), daemon=True)
        self.worker.start()

    def _run(self, data):
        from ..gap import GapSettings, GapWorkflow
        from ..gap.output import write_gap_outputs

        self.state = "running"
        try:
            flow = GapWorkflow(self.reference, GapSettings(max_effects=self.max_effects),
                               log=lambda text: self.get_logger().info(text))
            report = flow.run(data)
            if self.output_dir:
                write_gap_outputs(flow, report, data, self.output_dir)
            self.publisher.publish(gap_message(report, self.reference_name, self.get_clock().now().to_msg()))
            names = ", ".join(e["name"] for e in report["effects"]) or "none"
            self.get_logger().info(f"gap report: effects {names}; gap {report['gap_before']['overall']:.3f} % -> "
                                   f"{report['gap_after']['overall']:.3f} %")
            self.state = "done"
        except Exception as err:  # a failed analysis is reported, never kills the node
            self.state = "failed"
            self.last_error = f"gap workflow failed: {err}"
            self.get_logger().error(self.last_error)

    def _publish_diagnostics(self):
        values = dict(self.buffer.stats(), state=self.state, rejected_batches=self.rejected)
        level = DiagnosticStatus.WARN if self.last_error else DiagnosticStatus.OK
        publish_diagnostics(self, self.diagnostics, [status("pisml: gap", level, self.last_error or self.state, values)])


def main(args=None) -> int:
    return run_node(GapNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
