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


def residual_below(field: Callable, tol: float, scale) -> Callable[[np.ndarray, np.ndarray], bool]:
    """The acceptance test of a root: every component of f(x, u), divided by ``scale``, below ``tol``."""
    scale = np.asarray(scale, dtype=float)
    return lambda x, u: bool(np.max(np.abs(field(x, u)) / scale) < tol)


class EquilibriumNotFound(RuntimeError):
    """No equilibrium of the model at the requested inputs."""


def find_equilibrium(field: Callable, jacobian: Callable, inputs, reference_points=(), x0=None,
                     tol: float = 1e-9, scale=None, what: str = "model"):
    """Equilibrium f(x, u) = 0 of an identified model at ``inputs``.

    Starts from ``x0`` or from the stored reference points (``{"inputs", "state"}``) whose inputs
    are nearest, then follows the inputs from there in small steps (continuation).

    Raises
    ------
    EquilibriumNotFound
    """
    u = np.array(inputs, dtype=float)
    starts = []
    if x0 is not None:
        starts.append((u, np.asarray(x0, dtype=float)))
    refs = sorted(reference_points or [], key=lambda r: float(np.linalg.norm(np.asarray(r["inputs"]) - u)))
    starts += [(np.asarray(r["inputs"], dtype=float), np.asarray(r["state"], dtype=float)) for r in refs[:3]]
    if not starts:
        raise EquilibriumNotFound(f"{what}: no starting point for an equilibrium search (no reference points)")
    accept = residual_below(field, tol, 1.0 if scale is None else scale)
    for u_start, x_start in starts:
        x = root(field, jacobian, u_start, x_start, accept)
        if x is not None and not np.allclose(u_start, u):
            x = continuation(field, jacobian, u_start, x, u, 20, accept)
        if x is not None:
            return x
    raise EquilibriumNotFound(f"no equilibrium of the {what} at inputs {u.tolist()}")


def distinct_roots(field: Callable, jacobian: Callable, inputs, starts, known=(), box=None, tol: float = 1e-9,
                   scale=None, rtol: float = 1e-6) -> list:
    """The equilibria f(x, u) = 0 found from each of ``starts`` at the fixed ``inputs`` (no
    continuation; accepted as :func:`find_equilibrium` accepts one, by ``tol`` and ``scale``), other
    than the ``known`` ones and each other (apart by more than ``rtol`` relative to their size), and
    inside ``box`` = (low, high) where given.

    Returns
    -------
    list of ndarray
    """
    u = np.asarray(inputs, dtype=float)
    accept = residual_below(field, tol, 1.0 if scale is None else scale)
    found = [np.asarray(x, dtype=float) for x in known]
    new = []
    for start in starts:
        x = root(field, jacobian, u, np.asarray(start, dtype=float), accept)
        if x is None or box is not None and not np.all((box[0] <= x) & (x <= box[1])):
            continue
        if all(np.linalg.norm(x - y) > rtol * (1.0 + np.linalg.norm(y)) for y in found):
            found.append(x)
            new.append(x)
    return new
