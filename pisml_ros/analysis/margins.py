"""Stability margins along an operating-point parameter (e.g. the grid voltage)."""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import scipy.optimize


def stability_boundaries(max_real: Callable[[float], float], grid: Sequence[float], xtol: float = 1e-6) -> list[float]:
    """Values of a parameter where the least-damped eigenvalue crosses the imaginary axis.

    Parameters
    ----------
    max_real : callable
        Parameter value -> largest real part of the eigenvalues there (1/s).
        It may raise for values without an equilibrium; those are skipped.
    grid : sequence of float
        Increasing values to scan for sign changes; each bracket is refined with
        Brent's method.

    Returns
    -------
    list of float
        Crossing points, increasing.
    """
    values = []
    for g in grid:
        try:
            values.append((float(g), float(max_real(g))))
        except Exception:  # no equilibrium there: the scan just skips it
            continue
    crossings = []
    last = None  # the last grid value with a nonzero real part, and that part
    zeros = []  # grid values since then where the real part is exactly 0
    for g, m in values:
        if m == 0:
            zeros.append(g)
            continue
        if last is not None and np.sign(last[1]) != np.sign(m):
            # a crossing on a grid value counts once (not for the interval on each side of it)
            crossings.append(zeros[0] if zeros else float(scipy.optimize.brentq(max_real, last[0], g, xtol=xtol)))
        last, zeros = (g, m), []
    return crossings


def distance_to_boundary(value: float, boundaries: Sequence[float]) -> float:
    """Distance from ``value`` to the nearest boundary (inf when there is none)."""
    return float(min((abs(value - b) for b in boundaries), default=np.inf))


def root_locus(system, grid, theta_g: float = 0.0) -> dict:
    """Eigenvalues of ``system`` at its equilibria along ``grid`` (values of ug), and the
    stability boundaries (crossings of the imaginary axis, refined by Brent's method).

    Returns
    -------
    dict
        ``{"ug": [...], "theta_g", "eigenvalues": [[[re, im], ...] or None per ug],
        "max_real": [... or None], "boundaries": [...], "errors": {ug: message}}``
    """
    eig_at, errors = {}, {}
    eq_at: dict = {}  # equilibria found so far, by ug

    def max_real(g):
        g = float(g)
        if g not in eig_at:
            # from the nearest equilibrium found so far one root search usually suffices; the search
            # from the model's reference points (a 20-step continuation) is the fallback: 20x the cost
            near = min(eq_at, key=lambda h: abs(h - g)) if eq_at else None
            x = system.equilibrium(g, theta_g, x0=eq_at[near] if near is not None else None)
            eq_at[g] = x
            eig_at[g] = np.linalg.eigvals(system.jacobian(x, np.array([g, theta_g])))
        return float(np.max(eig_at[g].real))

    for g in grid:
        try:
            max_real(g)
        except Exception as err:  # no equilibrium there: recorded, the sweep goes on
            errors[f"{float(g):g}"] = str(err)
    boundaries = stability_boundaries(max_real, [float(g) for g in grid if float(g) in eig_at])
    out_eig, out_max = [], []
    for g in grid:
        lam = eig_at.get(float(g))
        if lam is None:
            out_eig.append(None)
            out_max.append(None)
        else:
            lam = lam[np.lexsort((-lam.imag, -lam.real))]
            out_eig.append([[float(z.real), float(z.imag)] for z in lam])
            out_max.append(float(np.max(lam.real)))
    return {"ug": [float(g) for g in grid], "theta_g": float(theta_g), "eigenvalues": out_eig, "max_real": out_max,
            "boundaries": boundaries, "errors": errors}
