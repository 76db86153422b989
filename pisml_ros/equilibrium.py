"""Equilibria of vector fields: Newton-type root finding with the exact Jacobian, and continuation
in the inputs (shared by the virtual HIL plant and explicit models)."""
from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.optimize


def root(field: Callable, jacobian: Callable, u, start, accept: Callable[[np.ndarray, np.ndarray], bool]):
    """f(x, u) = 0 from ``start`` (scipy hybrid Powell with the exact Jacobian); None unless ``accept(x, u)``."""
    sol = scipy.optimize.root(lambda x: field(x, u), start, jac=lambda x: jacobian(x, u), method="hybr",
                              options={"xtol": 1e-13})
    return sol.x if np.all(np.isfinite(sol.x)) and accept(sol.x, u) else None


def continuation(field: Callable, jacobian: Callable, u_from, x_from, u_to, steps: int,
                 accept: Callable[[np.ndarray, np.ndarray], bool]):
    """Follow the equilibrium from (u_from, x_from) to u_to in ``steps`` equal input steps; None if it is lost."""
    u_from, u_to = np.asarray(u_from, dtype=float), np.asarray(u_to, dtype=float)
    x = np.asarray(x_from, dtype=float)
    for level in np.linspace(0.0, 1.0, steps + 1)[1:]:
        x = root(field, jacobian, u_from + level * (u_to - u_from), x, accept)
        if x is None:
            return None
    return x
