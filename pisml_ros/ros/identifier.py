"""identifier node: assembles MeasurementBatch messages into trajectories.

This version buffers and validates (malformed batches are rejected with a
diagnostic; the node keeps running) and reports the buffer on /diagnostics.
The identification engine and the /pisml/model stages arrive with the engine
issue; the parameters that will drive it are declared already.
"""
from __future__ import annotations

from .common import MEASUREMENT_TOPIC, declare, measurement_qos, publish_diagnostics, run_node, status

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from pisml_msgs.msg import MeasurementBatch  # noqa: E402
from rclpy.node import Node  # noqa: E402

from ..data import DataError, validate_batch  # noqa: E402
from ..data.stream import TrajectoryBuffer  # noqa: E402


class IdentifierNode(Node):
    def __init__(self):
        super().__init__("identifier")
        self.min_trajectories = declare(self, "min_trajectories", 12,
                                        "complete trajectories needed before training starts", 1, 10000)
        self.method = declare(self, "method", "pisml", "pisml | std-sindy | mod-sindy | node | pisml-nojac")
        declare(self, "output_dir", "out/identifier", "where explicit models are saved (atomically)")
        max_samples = declare(self, "max_buffer_samples", 2_000_000, "samples kept in the buffer (oldest dropped)",
                              1000, 100_000_000)
        depth = declare(self, "qos_depth", 5000, "depth of the reliable measurement queue", 10, 1000000)
        self.buffer = TrajectoryBuffer(max_samples=max_samples)
        self.rejected = 0
        self.last_error = ""
        self.create_subscription(MeasurementBatch, MEASUREMENT_TOPIC, self._on_batch, measurement_qos(depth))
        self.diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(f"listening on {MEASUREMENT_TOPIC}; training needs {self.min_trajectories} trajectories")

    def _on_batch(self, msg: MeasurementBatch):
        try:
            arrays = validate_batch(msg, where="batch")
            event = self.buffer.add(int(msg.trajectory_id), int(msg.first_sample_index), float(msg.t0), arrays,
                                    bool(msg.end_of_trajectory))
        except DataError as err:
            self.rejected += 1
            self.last_error = str(err)
            self.get_logger().warning(f"rejected {err}")
            self._publish_diagnostics()
            return
        if event:
            self.get_logger().info(event)

    def _publish_diagnostics(self):
        values = dict(self.buffer.stats(), rejected_batches=self.rejected, stage="buffering",
                      last_error=self.last_error)
        level = DiagnosticStatus.WARN if self.last_error else DiagnosticStatus.OK
        publish_diagnostics(self, self.diagnostics,
                            [status("pisml: identifier", level, self.last_error or "buffering", values)])


def main(args=None) -> int:
    return run_node(IdentifierNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
