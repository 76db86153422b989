"""Message conversions between pisml_msgs and the core's plain Python objects."""
from __future__ import annotations

import math

import numpy as np
from pisml_msgs.msg import MeasurementBatch, ModeInfo, StabilityReport


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
