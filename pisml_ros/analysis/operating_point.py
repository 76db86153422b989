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
        "dominant_states": [...], "max_real": float, "min_damping": float, "stable": bool}``
    """
    x = system.equilibrium(ug, theta_g)
    a = system.jacobian(x, np.array([ug, theta_g]))
    names = tuple(system.state_names) + tuple(getattr(system, "hidden_state_names", ()))
    summary = modal_summary(a, names)
    report = {"operating_point": {"ug": float(ug), "theta_g": float(theta_g),
                                  "state": {n: float(v) for n, v in zip(names, x)}}}
    report.update(summary.to_dict())
    return report


def max_real_part(system, ug: float, theta_g: float = 0.0) -> float:
    """Largest real part of the eigenvalues at the equilibrium for (ug, theta_g)."""
    x = system.equilibrium(ug, theta_g)
    return float(np.max(np.linalg.eigvals(system.jacobian(x, np.array([ug, theta_g]))).real))


def ug_stability_margin(system, ug: float, theta_g: float = 0.0, ug_range=(0.2, 1.3), points: int = 23) -> dict:
    """Stability boundaries in grid voltage and the distance of ``ug`` to the nearest one."""
    grid = np.linspace(ug_range[0], ug_range[1], points)
    bounds = stability_boundaries(lambda g: max_real_part(system, g, theta_g), grid)
    return {"boundaries": bounds, "ug_margin": distance_to_boundary(ug, bounds)}


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


def growth_rates_at_points(model, points) -> list:
    """The largest real part of the eigenvalues (1/s) of an explicit ``model``'s equilibrium at each
    operating point of ``points`` (as :func:`stability_at_points`), None where no equilibrium was found."""
    from ..model import ExplicitModel

    probe = ExplicitModel(model.state_names, model.input_names, model.terms, model.coefficients,
                          {"reference_points": list(points)})
    rates = []
    for point in points:
        inputs = [float(v) for v in point["inputs"]]
        try:
            rates.append(float(np.max(probe.eigenvalues(*inputs).real)))
        except (RuntimeError, ValueError, np.linalg.LinAlgError, FloatingPointError):  # no equilibrium
            rates.append(None)
    return rates
