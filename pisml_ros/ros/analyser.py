"""analyser node: small-signal stability of identified models on /pisml/stability.

Subscribes to /pisml/model; for every IdentifiedModel that carries an explicit
model (``model_json``) it computes, at each operating point of ``ug_points``,
the equilibrium, eigenvalues, damping ratios, frequencies, dominant states and
the distance in ug to the nearest stability boundary, and publishes one
StabilityReport per point (transient-local, deep enough to hold them all) plus
/diagnostics (WARN below the damping / margin thresholds, ERROR when unstable or
when a model cannot be analysed). The analysis runs in a worker thread: a newer
model supersedes one still waiting.

Root locus: the eigenvalues over the ug sweep (``sweep_ug_min``..``sweep_ug_max``,
``sweep_points``) are published as JSON on /pisml/root_locus (std_msgs/String,
transient-local) and written to ``output_dir`` when set. Setting a ``sweep_*``
or ``ug_points`` parameter at run time re-runs the analysis of the latest model.

``analyse_plant`` reports on the virtual HIL plant at start-up (model_id "plant").

Microgrid: with ``microgrid_config`` (a ``pisml microgrid`` configuration file), every analysed
model also takes the place of unit ``microgrid_unit`` of that microgrid, and the microgrid's
report (operating point, each unit's voltage and power, the least-damped modes with each unit's
share) is published as JSON on /pisml/microgrid (std_msgs/String, transient-local) with a
diagnostic status (ERROR where the microgrid is unstable or has no operating point).
"""
from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path

import numpy as np

from .common import MODEL_TOPIC, STABILITY_TOPIC, declare, latched_qos, publish_diagnostics, run_node, status

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from pisml_msgs.msg import IdentifiedModel, StabilityReport  # noqa: E402
from rclpy.node import Node  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from ..analysis.margins import distance_to_boundary, root_locus  # noqa: E402
from ..analysis.operating_point import (alternatives_note, coverage_note, data_coverage,  # noqa: E402
                                         operating_point_report, other_equilibria_note, uncertainty_note)
from ..fileio import atomic_write_text  # noqa: E402
from .conversions import failed_stability_message, model_from_message, stability_message  # noqa: E402

ROOT_LOCUS_TOPIC = "/pisml/root_locus"
MICROGRID_TOPIC = "/pisml/microgrid"
SWEEP_PARAMETERS = ("ug_points", "sweep_ug_min", "sweep_ug_max", "sweep_points", "theta_g")


def warm_up() -> float:
    """Pay the analysis's one-time costs on a two-state model: the model module and sympy
    imported, term code generated, scipy's root finder and LAPACK called. The node's worker runs it
    at start-up, so that the first identified model's report comes as fast as the later ones.

    Measured (stop 37, 2 cores): a 78-coefficient model from import to report 0.42 s cold, 0.09 s
    after this; in the live graph (``bench/ros_bench.py``) the first report came 1.05 s after the
    backbone model before it (target 1 s), 0.40-0.44 s with it (two runs).

    Returns
    -------
    float
        Seconds it took.
    """
    started = time.monotonic()
    from ..model import ExplicitModel

    model = ExplicitModel(["x", "y"], ["ug", "theta_g"], ["x", "y", "ug*cos(theta_g - x)", "ug*sin(theta_g - x)"],
                          [[-1.0, 0.0], [0.0, -1.0], [0.1, 0.0], [0.0, 0.1]])
    operating_point_report(model, 0.8, 0.0)
    root_locus(model, np.linspace(0.2, 1.3, 3), 0.0)
    return time.monotonic() - started


class AnalyserNode(Node):
    def __init__(self):
        super().__init__("analyser")
        self.ug_points = self._check_points(list(declare(self, "ug_points", [0.8],
                                                         "grid voltages (p.u.) of the operating points")))
        self.theta_g = declare(self, "theta_g", 0.0, "grid voltage phase (rad) of the operating points", -3.15, 3.15)
        self.min_damping = declare(self, "min_damping_ratio", 0.05, "WARN below this damping ratio", 0.0, 1.0)
        self.min_ug_margin = declare(self, "min_ug_margin", 0.05, "WARN below this distance in ug to a boundary",
                                     0.0, 10.0)
        self.sweep = [declare(self, "sweep_ug_min", 0.2, "root locus / margin sweep: lowest ug (p.u.)", 0.01, 3.0),
                      declare(self, "sweep_ug_max", 1.3, "root locus / margin sweep: highest ug (p.u.)", 0.01, 3.0),
                      declare(self, "sweep_points", 23, "root locus / margin sweep: points (0 = no sweep, "
                              "no margins)", 0, 1000)]
        self._check_sweep(*self.sweep)
        self.output_dir = declare(self, "output_dir", "", "write stability.json and root_locus.json here "
                                  "(empty = no files)")
        self.analyse_plant = declare(self, "analyse_plant", False, "report on the virtual HIL plant at start-up")
        params_file = declare(self, "params_file", "", "plant parameter file for analyse_plant (empty = nameplate)")
        self.microgrid = self._load_microgrid(
            declare(self, "microgrid_config", "", "a `pisml microgrid` configuration: each model also replaces one "
                    "of its units and the microgrid's report goes to /pisml/microgrid (empty = off)"),
            declare(self, "microgrid_unit", "target", "the unit of microgrid_config the analysed models replace"))
        self.microgrid_pub = self.create_publisher(String, MICROGRID_TOPIC, latched_qos())
        # every operating point of a model stays latched for late subscribers
        self.stability = self.create_publisher(StabilityReport, STABILITY_TOPIC, latched_qos(
            depth=max(len(self.ug_points), 1)))
        self.locus = self.create_publisher(String, ROOT_LOCUS_TOPIC, latched_qos())
        self.diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.lock = threading.Condition()
        self.pending = None          # (system, model_id) waiting for the worker
        self.latest = None           # the last analysed (system, model_id): re-run on parameter changes
        self.statuses = []           # per operating point, of the last analysis
        self.analysed = 0
        self.last_error = ""
        self.failing = False         # the last error came after the last successful analysis
        self.state = "waiting for a model"
        self.add_post_set_parameters_callback(self._on_parameters)
        self.create_subscription(IdentifiedModel, MODEL_TOPIC, self._on_model, latched_qos())
        self.create_timer(1.0, self._publish_diagnostics)
        self.worker = threading.Thread(target=self._work, daemon=True, name="analyser-worker")
        self.worker.start()
        if self.analyse_plant:
            from ..plant import InverterPlant, PlantParameters, load_parameters

            plant = InverterPlant(load_parameters(params_file) if params_file else PlantParameters())
            self._submit(plant, "plant")

    # ------------------------------------------------------------------ parameters
    @staticmethod
    def _load_microgrid(path: str, unit: str):
        """(configuration, unit name, directory) of the microgrid, or None; a bad file stops the
        node at start-up with the file and entry named (microgrid_from_config's checks)."""
        if not path:
            return None
        from ..analysis.microgrid import MicrogridError, microgrid_from_config, read_microgrid_config

        try:
            config = read_microgrid_config(path)
        except MicrogridError as err:
            raise ValueError(f"parameter microgrid_config: {err}") from None
        microgrid_from_config(config, Path(path).parent, source=path)  # checked now, not at the first model
        names = [str(entry.get("name")) for entry in config["units"]]
        if unit not in names:
            raise ValueError(f"parameter microgrid_unit: {unit!r} is not a unit of {path} ({names})")
        return config, unit, Path(path).parent

    @staticmethod
    def _check_points(points):
        if not points or any(not (0.0 < ug < 3.0) for ug in points):
            raise ValueError(f"parameter ug_points: values must be in (0, 3) p.u., got {points}")
        return [float(ug) for ug in points]

    @staticmethod
    def _check_sweep(low, high, points):
        if points and not low < high:
            raise ValueError(f"parameters sweep_ug_min/sweep_ug_max: need min < max, got {low} and {high}")

    def _on_parameters(self, params):
        changed = {p.name: p.value for p in params if p.name in SWEEP_PARAMETERS}
        if not changed:
            return
        try:
            points = self._check_points(list(changed.get("ug_points", self.ug_points)))
            sweep = [changed.get("sweep_ug_min", self.sweep[0]), changed.get("sweep_ug_max", self.sweep[1]),
                     changed.get("sweep_points", self.sweep[2])]
            self._check_sweep(*sweep)
        except ValueError as err:
            self._error(str(err))
            return
        self.ug_points, self.sweep = points, sweep
        self.theta_g = float(changed.get("theta_g", self.theta_g))
        if self.latest is not None:
            self.get_logger().info(f"parameters {sorted(changed)} changed: analysing {self.latest[1]} again")
            self._submit(*self.latest)

    # ------------------------------------------------------------------ models in
    def _on_model(self, msg: IdentifiedModel):
        if not msg.model_json:
            self.get_logger().info(f"model {msg.model_id} ({msg.stage}) has no explicit form: not analysed")
            return
        try:
            model = model_from_message(msg)
            if len(model.input_names) != 2:
                raise ValueError(f"model {msg.model_id!r}: expected 2 inputs (grid magnitude, phase), got "
                                 f"{list(model.input_names)}")
        except Exception as err:  # a bad model is reported, never kills the node
            self._error(f"cannot analyse: {err}")
            return
        self.get_logger().info(f"model {msg.model_id} ({msg.stage}, {model.n_parameters} parameters) received")
        self._submit(model, msg.model_id)

    def _submit(self, system, model_id: str):
        with self.lock:
            self.pending = (system, model_id)
            self.lock.notify()

    def _work(self):
        try:
            self.get_logger().debug(f"analysis warmed up in {warm_up():.2f} s")
        except Exception as err:  # costs the first report its speed, nothing else
            self.get_logger().warning(f"analysis warm-up failed (the first report will be slower): {err}")
        while True:
            with self.lock:
                while self.pending is None:
                    self.lock.wait()
                job, self.pending = self.pending, None
            try:
                self.state = f"analysing {job[1]}"
                self.report_on(*job)
                self.latest = job
                self.analysed += 1
                self.state = f"analysed {job[1]}"
                self.failing = False
                self._publish_diagnostics()
            except Exception as err:  # anything unexpected is reported; the worker goes on
                self.state = "failed"
                self._error(f"{job[1]}: analysis failed: {err}")

    def _error(self, text: str):
        self.last_error, self.failing = text, True
        self.get_logger().error(text)
        self._publish_diagnostics()

    # ------------------------------------------------------------------ analysis
    def report_on(self, system, model_id: str):
        """Publish a StabilityReport per operating point, the root locus, and diagnostics on the margins."""
        theta_g, points = self.theta_g, list(self.ug_points)
        low, high, n = self.sweep
        locus = root_locus(system, np.linspace(low, high, n), theta_g) if n else None
        statuses, reports = [], {}
        names = tuple(system.state_names) + tuple(getattr(system, "hidden_state_names", ()))
        for ug in points:
            name = f"pisml: stability ug={ug:g}"
            stamp = self.get_clock().now().to_msg()
            try:
                report = operating_point_report(system, ug, theta_g)
            except Exception as err:  # a model without an equilibrium there must not stop the node
                self.stability.publish(failed_stability_message(model_id, ug, theta_g, f"no equilibrium: {err}",
                                                                names, stamp))
                statuses.append(status(name, DiagnosticStatus.ERROR, f"{model_id}: no equilibrium: {err}"))
                continue
            report["boundaries"] = locus["boundaries"] if locus else []
            report["ug_margin"] = distance_to_boundary(ug, locus["boundaries"]) if locus else math.nan
            reports[f"{ug:g}"] = report
            msg = stability_message(report, model_id, stamp)
            level, message = DiagnosticStatus.OK, "stable"
            if not report["stable"]:
                level, message = DiagnosticStatus.ERROR, "unstable"
            elif report["min_damping"] < self.min_damping or report["ug_margin"] < self.min_ug_margin:
                level, message = DiagnosticStatus.WARN, "margin below threshold"
            # a verdict within two standard deviations of the boundary is the model's, not the data's
            uncertainty = report.get("uncertainty")
            undecided = uncertainty_note(uncertainty)
            message += f" ({undecided})" if undecided else ""
            # other candidates that fit the records as well and disagree: the records do not decide
            rivals = alternatives_note(report.get("alternatives"))
            message += f" ({rivals})" if rivals else ""
            # a verdict outside the identification data rests on the model's extrapolation: say so
            note = coverage_note(report.get("data_coverage"))
            message += f" ({note})" if note else ""
            # a second equilibrium nearby: which one the inverter sits at depends on its history
            others = other_equilibria_note(report)
            message += "".join(f" ({line})" for line in others)
            msg.message = message
            self.stability.publish(msg)
            statuses.append(status(name, level, f"{model_id}: {message}", {
                "max_real_part": f"{report['max_real']:.6g}", "min_damping_ratio": f"{report['min_damping']:.6g}",
                "ug_margin": f"{report['ug_margin']:.6g}", "model_id": model_id,
                "extrapolated": str(bool(note)).lower(), "other_equilibria": str(len(others)),
                "verdict": "undetermined" if rivals else (
                    uncertainty["verdict"] if uncertainty else ("stable" if report["stable"] else "unstable"))}))
            self.get_logger().info(f"{model_id} at ug={ug:g}: {message}, max real part {report['max_real']:.4g} 1/s, "
                                   f"ug margin {report['ug_margin']:.4g}")
        if locus is not None:
            locus["model_id"] = model_id
            coverage = data_coverage(system, (low, theta_g))
            # where the boundaries rest on data: the inputs the model was identified on (None: unknown)
            locus["input_range"] = coverage["input_range"] if coverage else None
            self.locus.publish(String(data=json.dumps(locus)))
            bounds = [round(b, 4) for b in locus["boundaries"]]
            self.get_logger().info(f"{model_id}: stability boundaries in ug {bounds}")
        if self.microgrid is not None:
            statuses.append(self._report_microgrid(system, model_id))
        if self.output_dir:
            out = Path(self.output_dir)
            atomic_write_text(out / "stability.json", json.dumps(
                {"model_id": model_id, "theta_g": theta_g, "operating_points": reports}, indent=1,
                default=_json_float) + "\n")
            if locus is not None:
                atomic_write_text(out / "root_locus.json", json.dumps(locus, default=_json_float) + "\n")
        self.statuses = statuses

    def _report_microgrid(self, system, model_id: str):
        """The microgrid of ``microgrid_config`` with ``system`` as its unit ``microgrid_unit``:
        its report on /pisml/microgrid, and a diagnostic status."""
        from ..analysis.microgrid import microgrid_from_config, microgrid_report, with_unit_model

        config, unit, base = self.microgrid
        name = "pisml: microgrid"
        config, loaded = with_unit_model(config, unit, system, base)
        try:
            grid, inputs = microgrid_from_config(config, base, loaded=loaded)
            report = microgrid_report(grid, *inputs)
        except Exception as err:  # no operating point: reported, the node goes on
            text = f"{model_id} as microgrid unit {unit!r}: {err}"
            self.microgrid_pub.publish(String(data=json.dumps({"model_id": model_id, "unit": unit, "error": str(err)})))
            self.get_logger().error(text)
            return status(name, DiagnosticStatus.ERROR, text)
        report.update(model_id=model_id, unit=unit)
        self.microgrid_pub.publish(String(data=json.dumps(report, default=_json_float)))
        verdict = "stable" if report["stable"] else "unstable"
        undecided = uncertainty_note(report.get("uncertainty"))
        verdict += f" ({undecided})" if undecided else ""
        rivals = alternatives_note(report.get("alternatives"))
        verdict += f" ({rivals})" if rivals else ""
        deciding = report["weakest_modes"][0] if report["weakest_modes"] else {}
        if deciding.get("note"):  # the verdict rests on a mode faster than the unit's records pin
            verdict += f"; caution: {deciding['note']}"
        self.get_logger().info(f"{model_id} as microgrid unit {unit!r}: {verdict}, max real part "
                               f"{report['max_real']:.4g} 1/s")
        return status(name, DiagnosticStatus.OK if report["stable"] else DiagnosticStatus.ERROR,
                      f"{model_id} as unit {unit!r}: microgrid {verdict}",
                      {"max_real_part": f"{report['max_real']:.6g}", "model_id": model_id})

    def _publish_diagnostics(self):
        level = DiagnosticStatus.ERROR if self.failing else DiagnosticStatus.OK
        own = status("pisml: analyser", level, self.last_error if self.failing else self.state,
                     {"models_analysed": self.analysed, "state": self.state, "last_error": self.last_error})
        publish_diagnostics(self, self.diagnostics, [own] + list(self.statuses))


def _json_float(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(type(obj).__name__)


def main(args=None) -> int:
    return run_node(AnalyserNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
