"""analyser node: small-signal stability reports on /pisml/stability.

For each configured operating point (``ug_points``) it publishes a
StabilityReport (transient-local) with eigenvalues, damping, frequencies,
dominant states and the distance in ug to the nearest stability boundary,
and a /diagnostics WARN/ERROR when a margin is below its threshold. In this
version it analyses the virtual HIL plant (``analyse_plant``) and logs models
arriving on /pisml/model; analysing identified explicit models arrives with
the engine issue.
"""
from __future__ import annotations

from .common import MODEL_TOPIC, STABILITY_TOPIC, declare, latched_qos, publish_diagnostics, run_node

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue  # noqa: E402
from pisml_msgs.msg import IdentifiedModel, StabilityReport  # noqa: E402
from rclpy.node import Node  # noqa: E402

from ..analysis.operating_point import operating_point_report, ug_stability_margin  # noqa: E402
from .conversions import stability_message  # noqa: E402


class AnalyserNode(Node):
    def __init__(self):
        super().__init__("analyser")
        self.ug_points = list(declare(self, "ug_points", [0.8], "grid voltages (p.u.) of the operating points"))
        self.theta_g = declare(self, "theta_g", 0.0, "grid voltage phase (rad) of the operating points", -3.15, 3.15)
        self.min_damping = declare(self, "min_damping_ratio", 0.05, "WARN below this damping ratio", 0.0, 1.0)
        self.min_ug_margin = declare(self, "min_ug_margin", 0.05, "WARN below this distance in ug to a boundary",
                                     0.0, 10.0)
        self.analyse_plant = declare(self, "analyse_plant", False, "report on the virtual HIL plant at start-up")
        params_file = declare(self, "params_file", "", "plant parameter file for analyse_plant (empty = nameplate)")
        if any(not (0.0 < ug < 3.0) for ug in self.ug_points):
            raise ValueError(f"parameter ug_points: values must be in (0, 3) p.u., got {self.ug_points}")
        self.stability = self.create_publisher(StabilityReport, STABILITY_TOPIC, latched_qos())
        self.diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(IdentifiedModel, MODEL_TOPIC, self._on_model, latched_qos())
        if self.analyse_plant:
            from ..plant import InverterPlant, PlantParameters, load_parameters

            plant = InverterPlant(load_parameters(params_file) if params_file else PlantParameters())
            self.report_on(plant, "plant")

    def report_on(self, system, model_id: str):
        """Publish a StabilityReport per operating point, and diagnostics on the margins."""
        statuses = []
        for ug in self.ug_points:
            try:
                report = operating_point_report(system, ug, self.theta_g)
                report.update(ug_stability_margin(system, ug, self.theta_g))
            except Exception as err:  # a model without an equilibrium must not stop the node
                statuses.append(DiagnosticStatus(level=DiagnosticStatus.ERROR, name=f"pisml: stability ug={ug:g}",
                                                 message=f"{model_id}: {err}"))
                continue
            self.stability.publish(stability_message(report, model_id, self.get_clock().now().to_msg()))
            level, message = DiagnosticStatus.OK, "stable"
            if not report["stable"]:
                level, message = DiagnosticStatus.ERROR, "unstable"
            elif report["min_damping"] < self.min_damping or report["ug_margin"] < self.min_ug_margin:
                level, message = DiagnosticStatus.WARN, "margin below threshold"
            status = DiagnosticStatus(level=level, name=f"pisml: stability ug={ug:g}", message=f"{model_id}: {message}")
            status.values = [KeyValue(key="max_real_part", value=f"{report['max_real']:.6g}"),
                             KeyValue(key="min_damping_ratio", value=f"{report['min_damping']:.6g}"),
                             KeyValue(key="ug_margin", value=f"{report['ug_margin']:.6g}")]
            statuses.append(status)
            self.get_logger().info(f"{model_id} at ug={ug:g}: {message}, max real part {report['max_real']:.4g} 1/s")
        publish_diagnostics(self, self.diagnostics, statuses)

    def _on_model(self, msg: IdentifiedModel):
        self.get_logger().info(f"model {msg.model_id} ({msg.stage}) received; explicit-model analysis "
                               f"arrives with the engine")


def main(args=None) -> int:
    return run_node(AnalyserNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
