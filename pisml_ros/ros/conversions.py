"""Message conversions between pisml_msgs and the core's plain Python objects."""
from __future__ import annotations

import json
import math

import numpy as np
from pisml_msgs.msg import IdentifiedModel, MeasurementBatch, ModeInfo, StabilityReport  # noqa: F401

#: the message stages (IdentifiedModel.stage)
STAGES = ("backbone", "hybrid", "explicit")
HYBRID_NOTE = ("hybrid model = sparse backbone + neural residual N(x, u): it has no explicit form, so model_json, "
               "terms and coefficients are empty; the backbone equations below omit N")


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


def _finite_metrics(metrics: dict | None) -> tuple[list[str], list[float]]:
    names, values = [], []
    for key, value in (metrics or {}).items():
        try:
            value = float(value)
        except (TypeError, ValueError):
            continue
        names.append(str(key))
        values.append(value)
    return names, values


def model_message(model, stage: str, model_id: str, metrics: dict | None = None, stamp=None) -> IdentifiedModel:
    """An IdentifiedModel for one stage of an identification run.

    ``model`` is an :class:`~pisml_ros.model.ExplicitModel` (its JSON travels in
    ``model_json``), a hybrid model with a ``backbone`` ExplicitModel (no JSON: the
    backbone alone is not a correct description; the equations say so), or any other
    model (e.g. a neural ODE: names and metrics only).
    """
    from ..model import ExplicitModel

    if stage not in STAGES:
        raise ValueError(f"stage {stage!r} is not one of {STAGES}")
    msg = IdentifiedModel()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.header.frame_id = "pisml"
    msg.model_id = str(model_id)
    msg.stage = stage
    metrics = dict(metrics or {})
    if isinstance(model, ExplicitModel):
        msg.state_names = list(model.state_names)
        msg.input_names = list(model.input_names)
        msg.terms = list(model.terms)
        msg.coefficients = np.ascontiguousarray(model.coefficients, dtype=float).ravel().tolist()
        msg.equations = model.equations()
        msg.n_parameters = int(model.n_parameters)
        msg.model_json = model.to_json()
    else:
        backbone = getattr(model, "backbone", None)
        names_from = backbone if isinstance(backbone, ExplicitModel) else model
        msg.state_names = [str(n) for n in getattr(names_from, "state_names", ())]
        msg.input_names = [str(n) for n in getattr(names_from, "input_names", ())]
        if isinstance(backbone, ExplicitModel):
            msg.equations = [HYBRID_NOTE] + [f"{eq} + N_{name}(x, u)"
                                             for eq, name in zip(backbone.equations(), backbone.state_names)]
            metrics.setdefault("backbone_n_parameters", backbone.n_parameters)
        else:
            msg.equations = [f"{type(model).__name__}: no explicit form"]
        n_params = getattr(model, "n_parameters", 0)
        msg.n_parameters = int(n_params) if n_params is not None else 0
    msg.metric_names, msg.metric_values = _finite_metrics(metrics)
    return msg


def message_metrics(msg) -> dict:
    """The metrics of an IdentifiedModel (or an Identify result) as a dict."""
    return dict(zip(msg.metric_names, msg.metric_values))


def model_from_message(msg):
    """The ExplicitModel carried by an IdentifiedModel.

    Raises
    ------
    ModelFormatError
        Empty or malformed ``model_json`` (the message names the model and the field).
    """
    from ..model import ExplicitModel, ModelFormatError

    where = f"model {msg.model_id!r} ({msg.stage})"
    if not msg.model_json:
        raise ModelFormatError(f"{where}: model_json is empty")
    try:
        data = json.loads(msg.model_json)
    except json.JSONDecodeError as err:
        raise ModelFormatError(f"{where}: model_json is not valid JSON ({err.msg} at line {err.lineno})") from None
    return ExplicitModel.from_dict(data, source=where)


def overrides_from_fields(names, values, where: str = "overrides") -> dict:
    """``override_names``/``override_values`` (strings side by side) as a settings mapping.

    Values that parse as JSON become numbers, booleans, lists or mappings; anything else stays a string.
    """
    names, values = list(names), list(values)
    if len(names) != len(values):
        raise ValueError(f"{where}: {len(names)} names but {len(values)} values")
    out = {}
    for name, value in zip(names, values):
        if not name:
            raise ValueError(f"{where}: empty name")
        try:
            out[str(name)] = json.loads(value)
        except (TypeError, ValueError):
            out[str(name)] = value
    return out


def overrides_from_assignments(items, where: str = "overrides") -> dict:
    """``["epochs=20", "refine=false"]`` as a settings mapping (values parsed as in :func:`overrides_from_fields`)."""
    from ..ident.config import settings_from_assignments

    pairs = settings_from_assignments(items, where)
    return overrides_from_fields(list(pairs), list(pairs.values()), where)


def failed_stability_message(model_id: str, ug: float, theta_g: float, error: str, state_names=(),
                             stamp=None, input_names=("ug", "theta_g")) -> StabilityReport:
    """A StabilityReport for an operating point where the model has no equilibrium (``equilibrium_found`` false)."""
    msg = StabilityReport()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.model_id = model_id
    msg.input_names = list(input_names)
    msg.input_values = [float(ug), float(theta_g)]
    msg.state_names = list(state_names)
    msg.equilibrium_found = False
    msg.max_real_part = math.nan
    msg.min_damping_ratio = math.nan
    msg.stable = False
    msg.ug_margin = math.nan
    msg.message = str(error)
    return msg


def stability_dict(msg) -> dict:
    """A StabilityReport as a JSON-ready dict (the shape of ``operating_point_report`` plus the margin)."""
    return {
        "model_id": msg.model_id,
        "operating_point": dict(zip(msg.input_names, msg.input_values),
                                state=dict(zip(msg.state_names, msg.equilibrium))),
        "equilibrium_found": bool(msg.equilibrium_found),
        "eigenvalues": [[float(re), float(im)] for re, im in zip(msg.eigenvalues_real, msg.eigenvalues_imag)],
        "damping": [float(z) for z in msg.damping_ratios],
        "frequencies_hz": [float(f) for f in msg.frequencies],
        "dominant_states": [list(m.dominant_states) for m in msg.modes],
        "max_real": float(msg.max_real_part),
        "min_damping": float(msg.min_damping_ratio),
        "stable": bool(msg.stable),
        "ug_margin": float(msg.ug_margin),
        "message": msg.message,
    }
