"""Small-signal report of any dynamic system at an operating point.

Works with any object offering ``equilibrium(ug, theta_g)``,
``jacobian(x, u)`` and ``state_names`` (the virtual HIL plant today, explicit
models later): duck typing keeps this module free of the plant.
"""
from __future__ import annotations

import numpy as np

from .margins import distance_to_boundary, stability_boundaries
from .modal import modal_summary


def operating_point_report(system, ug: float, theta_g: float = 0.0) -> dict:
    """Equilibrium, eigenvalues, damping and stability at (ug, theta_g), JSON-ready.

    Returns
    -------
    dict
        ``{"operating_point": {"ug", "theta_g", "state": {name: value}},
        "eigenvalues": [[re, im], ...], "damping": [...], "frequencies_hz": [...],
        "dominant_states": [...], "max_real": float, "min_damping": float, "stable": bool}``, plus
        ``"data_coverage"`` (:func:`data_coverage`), ``"uncertainty"`` (:func:`verdict_uncertainty`)
        and ``"alternatives"`` (:func:`alternative_verdicts`) where the system carries them
        (identified models).
    """
    return analyse_operating_point(system, ug, theta_g)[0]


def analyse_operating_point(system, ug: float, theta_g: float = 0.0) -> tuple:
    """:func:`operating_point_report` with what it computed on the way, for callers that build
    on it (the microgrid's report) without solving the equilibrium and the eigenproblem again.

    Returns
    -------
    report : dict
        As :func:`operating_point_report`.
    x : ndarray
        The equilibrium.
    summary : ModalSummary
        The modal summary of the Jacobian there (participation factors included).
    """
    x = system.equilibrium(ug, theta_g)
    a = system.jacobian(x, np.array([ug, theta_g]))
    names = tuple(system.state_names) + tuple(getattr(system, "hidden_state_names", ()))
    summary = modal_summary(a, names)
    report = {"operating_point": {"ug": float(ug), "theta_g": float(theta_g),
                                  "state": {n: float(v) for n, v in zip(names, x)}}}
    report.update(summary.to_dict())
    coverage = data_coverage(system, (ug, theta_g))
    if coverage is not None:
        report["data_coverage"] = coverage
    uncertainty = verdict_uncertainty(system, x, (ug, theta_g), report["max_real"])
    if uncertainty is not None:
        report["uncertainty"] = uncertainty
    alternatives = alternative_verdicts(system, x, (ug, theta_g), report["max_real"])
    if alternatives is not None:
        report["alternatives"] = alternatives
    others = other_equilibria(system, (ug, theta_g), x, names)
    if others:
        report["other_equilibria"] = others
    return report, x, summary


def alternative_verdicts(system, x, inputs, max_real: float) -> dict | None:
    """What the candidates that reproduced the identification records about as well as the model
    (:meth:`~pisml_ros.model.explicit.ExplicitModel.alternatives`; for an assembled microgrid, its
    identified units', one swapped in at a time: ``system.alternative_max_reals``) say at this
    operating point: each one's largest real part at its own equilibrium near ``x`` (None: none
    found there), and whether every one gives the model's verdict (``agree``). Where they do not,
    the records do not decide stability here: the covariance of :func:`verdict_uncertainty` counts
    the noise alone, for one set of terms. None where the system carries no alternatives (the
    plant, baselines, models identified before stop 62). Where an entry cannot be rebuilt, the
    dict says so (``"error"``) and the rest of the report stands."""
    from ..model import ModelFormatError

    u = np.asarray(inputs, dtype=float)
    assembled = getattr(system, "alternative_max_reals", None)
    alternatives = getattr(system, "alternatives", None)
    if not callable(assembled) and not callable(alternatives):
        return None
    try:
        if callable(assembled):
            found = assembled(x, u)
        else:
            found = [{"name": name, "max_real": max_real_near(model, x, u)} for name, model in alternatives()]
    except ModelFormatError as err:  # a damaged entry costs the alternatives, not the report
        return {"candidates": [], "agree": False, "max_real_range": [max_real, max_real], "error": str(err)}
    if not found:
        return None
    values = [item["max_real"] for item in found if item["max_real"] is not None]
    return {"candidates": found, "agree": not any(verdict_differs(max_real, item["max_real"]) for item in found),
            "max_real_range": [min(values + [max_real]), max(values + [max_real])],
            "basis": "the fit's candidates within the selection's tolerance of the best training error"}


def max_real_near(system, x0, inputs) -> float | None:
    """The largest real part of ``system``'s eigenvalues at its equilibrium for ``inputs`` (ug,
    theta_g) found from ``x0`` (another model's operating point, followed), or None where none is
    found there: one alternative's verdict (:func:`alternative_verdicts`,
    :meth:`~pisml_ros.analysis.microgrid.Microgrid.alternative_max_reals`)."""
    from ..equilibrium import EquilibriumNotFound

    u = np.asarray(inputs, dtype=float)
    try:
        y = system.equilibrium(*(float(v) for v in u), x0=x0)
        return float(np.linalg.eigvals(system.jacobian(y, u)).real.max())
    except (EquilibriumNotFound, ValueError, np.linalg.LinAlgError):
        return None


def verdict_differs(max_real: float | None, other: float | None) -> bool:
    """Whether two largest real parts (None: no operating point) give different stability
    verdicts: one stable and one not, or one with an operating point and one without."""
    if max_real is None or other is None:
        return (max_real is None) != (other is None)
    return (max_real < 0) != (other < 0)


def uncertainty_note(uncertainty: dict | None) -> str:
    """A line on ``report["uncertainty"]`` where the verdict is within two standard deviations of
    the boundary (the model's guess, not the data's), else ``""``."""
    if not uncertainty or uncertainty["verdict"] != "undetermined":
        return ""
    low, high = uncertainty["max_real_interval"]
    return f"not decided by the data: max real part {low:.3g} .. {high:.3g} 1/s, 2 std"


def alternatives_note(alternatives: dict | None) -> str:
    """A line on ``report["alternatives"]`` (:func:`alternative_verdicts`) where the candidates
    disagree with the model's verdict, else ``""``."""
    if not alternatives or alternatives["agree"]:
        return ""
    if "error" in alternatives:
        return f"the model's alternatives could not be read ({alternatives['error']})"
    low, high = alternatives["max_real_range"]
    missing = sum(item["max_real"] is None for item in alternatives["candidates"])
    return (f"stability not decided by the records: {len(alternatives['candidates'])} candidate(s) that fit them "
            f"about as well put the largest real part at {low:.3g} .. {high:.3g} 1/s"
            + (f" ({missing} without an equilibrium here)" if missing else ""))


def other_equilibria(system, inputs, x, names) -> list | None:
    """The system's other equilibria near its identification records at ``inputs``
    (``system.other_equilibria``, identified models), nearest first: ``[{"distance", "max_real",
    "stable", "differs_most" (the three states furthest from ``x``), "state"}]``; None where the
    system cannot say (the plant, an assembled microgrid)."""
    find = getattr(system, "other_equilibria", None)
    found = find(inputs, x) if callable(find) else None
    if found is None:
        return None
    u, out = np.asarray(inputs, dtype=float), []
    for y in found:
        max_real = float(np.linalg.eigvals(system.jacobian(y, u)).real.max())
        order = np.argsort(-np.abs(y - x))[:3]
        out.append({"distance": float(np.linalg.norm(y - x)), "max_real": max_real, "stable": bool(max_real < 0),
                    "differs_most": [names[k] for k in order], "state": {n: float(v) for n, v in zip(names, y)}})
    return sorted(out, key=lambda item: item["distance"])


def other_equilibria_note(report: dict, found: str = "another equilibrium of the model",
                          which: str = "the report is for the one followed from the records' rest states, and "
                                       "which one the inverter sits at") -> list:
    """Lines on ``report["other_equilibria"]`` (:func:`operating_point_report`; a microgrid report's
    unit entry), one per equilibrium: ``found``, where it is and how stable, then ``which`` (the
    one reported) "depends on how it got there"."""
    return [f"{found} {item['distance']:.3g} away in state (most in {', '.join(item['differs_most'])}), "
            f"{'stable' if item['stable'] else 'unstable'} (largest real part {item['max_real']:+.4g} 1/s): "
            f"{which} depends on how it got there"
            for item in report.get("other_equilibria") or []]


def verdict_uncertainty(system, x, inputs, max_real: float) -> dict | None:
    """How far the identification data pin the stability verdict at an equilibrium ``x``:
    ``{"max_real_std", "max_real_interval" (± VERDICT_SIGMAS std), "verdict" (stable, unstable or
    undetermined), "basis"}`` from the model's coefficient covariance
    (:mod:`~pisml_ros.analysis.uncertainty`); None where the system carries none (the plant, the
    baselines, models saved before it was recorded)."""
    from .uncertainty import VERDICT_SIGMAS, coefficient_covariance, max_real_std, stability_verdict

    own = getattr(system, "max_real_std", None)
    if callable(own):  # an assembled system (a microgrid) carries its identified parts' covariances
        std, basis = own(x, np.asarray(inputs, dtype=float)), getattr(system, "uncertainty_basis", "")
    else:
        stored = coefficient_covariance(system)
        if stored is None:
            return None
        std = max_real_std(system, x, np.asarray(inputs, dtype=float), stored)
        basis = system.metadata["coefficient_covariance"].get("basis", "")
    if std is None:
        return None
    return {"max_real_std": std,
            "max_real_interval": [max_real - VERDICT_SIGMAS * std, max_real + VERDICT_SIGMAS * std],
            "verdict": stability_verdict(max_real, std), "basis": basis}


def identified_input_range(system) -> dict | None:
    """The inputs an identified model was fitted on, ``{input: [min, max]}`` from its
    ``metadata["training"]["input_range"]``, without the grid phase (role ``grid_phase`` of the
    model's configuration: the equations see it only relative to the inverter's angle, so every
    phase is covered). None where the system carries no range (the plant; models identified
    before the range was recorded)."""
    metadata = getattr(system, "metadata", None) or {}
    ranges = (metadata.get("training") or {}).get("input_range")
    if not ranges:
        return None
    phase = ((metadata.get("config") or {}).get("roles") or {}).get("grid_phase", "theta_g")
    return {name: [float(low), float(high)] for name, (low, high) in ranges.items() if name != phase}


def data_coverage(system, inputs) -> dict | None:
    """Whether an operating point lies inside the inputs an identified model was fitted on.

    Parameters
    ----------
    system
        An identified model (see :func:`identified_input_range`).
    inputs : sequence of float
        The operating point, in the order of ``system.input_names``.

    Returns
    -------
    dict or None
        ``{"input_range": {input: [min, max]}, "outside": [inputs out of range], "extrapolated":
        bool}``; None where the system carries no range.
    """
    ranges = identified_input_range(system)
    if ranges is None:
        return None
    outside = []
    for name, value in zip(system.input_names, inputs):
        if name in ranges:
            low, high = ranges[name]
            tolerance = 1e-9 * max(1.0, abs(low), abs(high))
            if not low - tolerance <= float(value) <= high + tolerance:
                outside.append(name)
    return {"input_range": ranges, "outside": outside, "extrapolated": bool(outside)}


def coverage_note(coverage: dict | None) -> str:
    """One line on an extrapolated operating point (``report["data_coverage"]`` of
    :func:`operating_point_report`), e.g. ``"extrapolated: outside the identification data's ug
    0.64-1.2"``; empty where the point is covered or nothing is known."""
    if not coverage or not coverage.get("extrapolated"):
        return ""
    ranges = coverage["input_range"]
    return "extrapolated: outside the identification data's " + ", ".join(
        f"{name} {ranges[name][0]:.4g}-{ranges[name][1]:.4g}" for name in coverage["outside"])


#: a mode faster than this fraction of an identified model's sample rate gets a note: with fewer
#: than four samples per period its records hardly pin the damping (a rule of thumb, see
#: :func:`bandwidth_note`)
BANDWIDTH_FRACTION = 0.25


def bandwidth_note(system, frequency_hz: float, name: str = "the model") -> str:
    """One line on a mode faster than :data:`BANDWIDTH_FRACTION` of the sample rate of the records
    ``system`` was identified on (``metadata["training"]["sample_period"]``), e.g. ``"3857 Hz:
    above 0.25 x the sample rate of target's records (10000 Hz), so its damping rests on what
    they hardly pin"``; empty below it, or where the system carries no sample period (the
    plant, models saved before it was recorded).

    Such a mode appears where a network resonance meets an identified unit (a capacitor at its
    terminals, a line): the unit's equations are then evaluated on fast dynamics its records only
    graze. Measured (README, "Grid strength"): one of the 40 dB models puts a 3.9 kHz network
    resonance at +51 1/s where the plant damps it at −170 1/s.
    """
    metadata = getattr(system, "metadata", None) or {}
    period = (metadata.get("training") or {}).get("sample_period")
    if not period or not frequency_hz > BANDWIDTH_FRACTION / float(period):
        return ""
    return (f"{frequency_hz:.0f} Hz: above {BANDWIDTH_FRACTION:g} x the sample rate of {name}'s records "
            f"({1.0 / float(period):.0f} Hz), so its damping rests on what they hardly pin")


def max_real_part(system, ug: float, theta_g: float = 0.0) -> float:
    """Largest real part of the eigenvalues at the equilibrium for (ug, theta_g)."""
    return _equilibrium_and_max_real(system, ug, theta_g)[1]


def _equilibrium_and_max_real(system, ug: float, theta_g: float = 0.0) -> tuple:
    """The equilibrium for (ug, theta_g) and the largest real part of the eigenvalues there."""
    x = system.equilibrium(ug, theta_g)
    return x, float(np.max(np.linalg.eigvals(system.jacobian(x, np.array([ug, theta_g]))).real))


def ug_stability_margin(system, ug: float, theta_g: float = 0.0, ug_range=(0.2, 1.3), points: int = 23) -> dict:
    """Stability boundaries in grid voltage and the distance of ``ug`` to the nearest one (and,
    for a system with a coefficient covariance, :func:`undetermined_ug_ranges`)."""
    grid = np.linspace(ug_range[0], ug_range[1], points)
    solved: dict = {}  # the grid's equilibria serve both scans

    def at(g):
        if g not in solved:
            solved[g] = _equilibrium_and_max_real(system, g, theta_g)
        return solved[g]

    bounds = stability_boundaries(lambda g: at(g)[1], grid)
    out = {"boundaries": bounds, "ug_margin": distance_to_boundary(ug, bounds)}
    undetermined = undetermined_ug_ranges(system, grid, theta_g, solve=at)
    if undetermined is not None:
        out["undetermined_ug"] = undetermined
    return out


def undetermined_ug_ranges(system, grid, theta_g: float = 0.0, solve=None) -> list | None:
    """The stretches ``[first, last]`` of the grid voltages ``grid`` where the identification data do
    not decide the stability verdict (:func:`verdict_uncertainty`: "undetermined"); None where the
    system carries no coefficient covariance. A boundary found inside such a stretch is where the
    model puts it, not where the data pin it. ``solve(g) -> (equilibrium, largest real part)``:
    where the caller has them already."""
    from .uncertainty import coefficient_covariance

    if coefficient_covariance(system) is None:
        return None
    solve = solve or (lambda g: _equilibrium_and_max_real(system, g, theta_g))
    ranges: list = []
    previous = False
    for g in grid:
        try:
            x, max_real = solve(float(g))
            verdict = (verdict_uncertainty(system, x, (g, theta_g), max_real) or {}).get("verdict")
        except (RuntimeError, ValueError, np.linalg.LinAlgError, FloatingPointError):  # no equilibrium
            verdict = None
        if verdict == "undetermined":
            if previous:
                ranges[-1][1] = float(g)
            else:
                ranges.append([float(g), float(g)])
        previous = verdict == "undetermined"
    return ranges


def stability_at_points(model, points) -> list:
    """Stability of an explicit ``model`` at each operating point of ``points`` (dicts with
    ``inputs`` and ``state``, as a model's ``metadata["reference_points"]``; they also seed the
    equilibrium search).

    Returns
    -------
    list of bool or None
        Per point: True if the equilibrium there has no eigenvalue with a real part >= 0, False if it
        has, None where no equilibrium was found.
    """
    return [None if growth is None else bool(growth < 0) for growth in growth_rates_at_points(model, points)]


def growth_rates_at_points(model, points, at=None, zero_mode_below: float = 0.0) -> list:
    """The largest real part of the eigenvalues (1/s) of an explicit ``model``'s equilibrium at each
    operating point of ``points`` (as :func:`stability_at_points`), None where no equilibrium was found.
    ``at``: input vectors to evaluate at instead, the equilibrium search still seeded by ``points``.
    ``zero_mode_below``: an equilibrium with a mode of modulus below this (1/s) counts as none
    (None): with a Jacobian all but singular, the smallest offset in f moves it far (Δx ≈ J⁻¹ Δf)
    and its linear analysis cannot tell growth from decay."""
    return [rate for _, rate in equilibria_at_points(model, points, at=at, zero_mode_below=zero_mode_below)]


def equilibria_at_points(model, points, at=None, zero_mode_below: float = 0.0) -> list:
    """Per point of ``points`` (or of ``at``, as :func:`growth_rates_at_points`): ``(x, rate)``, the
    equilibrium ``model`` has there (None where none was found) and its largest real part of the
    eigenvalues (None also where the equilibrium has a zero mode, ``zero_mode_below``). For a caller
    that needs both, so that each equilibrium is solved once."""
    from ..model import ExplicitModel

    probe = ExplicitModel(model.state_names, model.input_names, model.terms, model.coefficients,
                          {"reference_points": list(points)})
    found = []
    for point in (points if at is None else [{"inputs": inputs} for inputs in at]):
        inputs = [float(v) for v in point["inputs"]]
        try:
            x = probe.equilibrium(*inputs)
            eigenvalues = np.linalg.eigvals(probe.jacobian(x, np.array(inputs, dtype=float)))
        except (RuntimeError, ValueError, np.linalg.LinAlgError, FloatingPointError):  # no equilibrium
            found.append((None, None))
            continue
        zero_mode = np.min(np.abs(eigenvalues), initial=np.inf) < zero_mode_below
        found.append((x, None if zero_mode else float(np.max(eigenvalues.real))))
    return found


class _TooSlow(Exception):
    """An integration that needs more right-hand-side evaluations than allowed."""


def rest_drift(model, point, horizon: float, tolerance: float, max_evaluations: int = 5000) -> float:
    """How far ``model``, run freely from a rest state with its inputs held, moves from it within
    ``horizon`` seconds, as the largest ‖x(t) − x_rest‖ / ‖x_rest‖ (the run stops once it exceeds
    ``tolerance``: only whether it stays within matters).

    For a model without an equilibrium near a point where a record sat at rest (a fold of its
    equilibrium branch just before the point, say): it may pass the point as slowly as a model
    whose equilibrium there is weakly unstable. Integrated by scipy's BDF with the model's Jacobian
    (the fast filter modes make explicit steps tiny over a horizon of seconds).

    Parameters
    ----------
    model
        Anything with ``vector_field(x, u)`` and ``jacobian(x, u)``.
    point : dict
        ``{"inputs", "state"}`` (as a model's ``metadata["reference_points"]``).
    horizon : float
        Seconds.
    tolerance : float
        The relative drift at which the run stops.
    max_evaluations : int
        A run that needs more evaluations of the vector field (a fast oscillation, say) counts as
        leaving: inf.

    Returns
    -------
    float
        The largest relative drift seen (at least ``tolerance`` where the run stopped early); inf
        where the integration fails, leaves finite values or runs out of evaluations.
    """
    import scipy.integrate

    x0 = np.asarray(point["state"], dtype=float)
    u = np.asarray(point["inputs"], dtype=float)
    size = max(float(np.linalg.norm(x0)), 1e-12)
    calls = [0]

    def field(_t, x):
        calls[0] += 1
        if calls[0] > max_evaluations:
            raise _TooSlow
        return model.vector_field(x, u)

    def leaves(_t, x):
        return np.linalg.norm(x - x0) / size - tolerance

    leaves.terminal = True
    try:
        with np.errstate(all="ignore"):
            sol = scipy.integrate.solve_ivp(field, (0.0, horizon), x0, method="BDF", events=leaves,
                                            jac=lambda _t, x: model.jacobian(x, u), rtol=1e-6, atol=1e-9)
    except (_TooSlow, FloatingPointError, ValueError, np.linalg.LinAlgError):
        return float("inf")
    if sol.status < 0 or not np.all(np.isfinite(sol.y)):
        return float("inf")
    return float(np.max(np.linalg.norm(sol.y - x0[:, None], axis=0)) / size)
