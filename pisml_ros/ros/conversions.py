"""Message conversions between pisml_msgs and the core's plain Python objects."""
from __future__ import annotations

import math

import numpy as np
from pisml_msgs.msg import MeasurementBatch, ModeInfo, StabilityReport  # noqa: F401


def batch_message(traj, start: int, stop: int, last: bool, dt: float, state_names, input_names, stamp=None):
    """A MeasurementBatch holding samples [start, stop) of a trajectory."""
    msg = MeasurementBatch()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = "pisml"
    msg.trajectory_id = int(traj.traj_id)
    msg.first_sample_index = int(start)
    msg.t0 = float(traj.t[start])
    msg.dt = float(dt)
    msg.end_of_trajectory = bool(last)
    msg.state_names = list(state_names)
    msg.input_names = list(input_names)
    msg.x = np.ascontiguousarray(traj.x[start:stop], dtype=float).ravel().tolist()
    msg.u = np.ascontiguousarray(traj.u[start:stop], dtype=float).ravel().tolist()
    return msg


def stability_message(report: dict, model_id: str, stamp=None, input_names=("ug", "theta_g")) -> StabilityReport:
    """A StabilityReport from :func:`pisml_ros.analysis.operating_point.operating_point_report`."""
    msg = StabilityReport()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.model_id = model_id
    op = report["operating_point"]
    msg.input_names = list(input_names)
    msg.input_values = [float(op["ug"]), float(op["theta_g"])]
    msg.state_names = list(op["state"])
    msg.equilibrium = [float(v) for v in op["state"].values()]
    msg.equilibrium_found = True
    msg.eigenvalues_real = [float(re) for re, _ in report["eigenvalues"]]
    msg.eigenvalues_imag = [float(im) for _, im in report["eigenvalues"]]
    msg.damping_ratios = [float(z) for z in report["damping"]]
    msg.frequencies = [float(f) for f in report["frequencies_hz"]]
    for (re, im), zeta, freq, dom in zip(report["eigenvalues"], report["damping"], report["frequencies_hz"],
                                          report["dominant_states"]):
        msg.modes.append(ModeInfo(real=float(re), imag=float(im), damping_ratio=float(zeta),
                                  frequency=float(freq), dominant_states=list(dom)))
    msg.max_real_part = float(report["max_real"])
    msg.min_damping_ratio = float(report["min_damping"])
    msg.stable = bool(report["stable"])
    msg.ug_margin = float(report.get("ug_margin", math.nan))
    return msg


def gap_message(report: dict, reference: str, stamp=None):
    """A GapReport from the gap workflow's report dict."""
    import json

    from pisml_msgs.msg import GapEffect, GapReport, GapWindow

    msg = GapReport()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.reference = reference
    for w in report["windows"]:
        cond = w.get("conditions", {})
        msg.windows.append(GapWindow(trajectory_id=int(w["traj"]), t0=float(w["t0"]), t1=float(w["t1"]),
                                     states=list(w["states"]), condition_names=list(cond),
                                     condition_values=[float(v) for v in cond.values()]))
    for e in report["effects"]:
        eff = GapEffect(name=e["name"])
        numeric = {k: v for k, v in e["params"].items() if isinstance(v, (int, float))}
        eff.param_names = list(numeric) + ([f"parameter={e['params']['parameter']}"] if "parameter" in e["params"] else [])
        eff.param_values = [float(v) for v in numeric.values()] + ([math.nan] if "parameter" in e["params"] else [])
        eff.param_uncertainty = [float(e["uncertainty"].get(k, math.nan)) for k in numeric] + \
            ([math.nan] if "parameter" in e["params"] else [])
        evidence = {k: v for k, v in e["evidence"].items() if isinstance(v, (int, float))}
        eff.evidence_names = list(evidence)
        eff.evidence_values = [float(v) for v in evidence.values()]
        msg.effects.append(eff)
    msg.gap_before = float(report["gap_before"]["overall"])
    msg.gap_after = float(report["gap_after"]["overall"])
    msg.noise_level = float(report["noise_level"]["relative_median"])
    msg.effect_missing = bool(report["effects"])
    msg.report_json = json.dumps(report, default=float)
    return msg
