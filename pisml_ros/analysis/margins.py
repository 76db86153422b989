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
