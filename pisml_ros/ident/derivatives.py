"""Derivative and integral-form regression matrices from sampled trajectories."""
from __future__ import annotations

import numpy as np

from ..data import Dataset
from ..model.expressions import TermSet


def finite_difference_derivatives(dataset: Dataset, order: int = 2) -> list[np.ndarray]:
    """dx/dt per trajectory by pysindy's finite differences."""
    import pysindy as ps

    diff = ps.FiniteDifference(order=order)
    return [diff._differentiate(tr.x, tr.t) for tr in dataset]


def integral_form(dataset: Dataset, terms: TermSet, span: int = 10, stride: int = 1):
    """Integral (weak) form of dx/dt = Θ(x, u) C over windows of ``span`` samples.

    x(t_{k+span}) - x(t_k) = ∫ Θ dt · C, with the integral by the trapezoid rule: a
    linear least-squares problem A C = B that, unlike derivatives, averages the noise.

    Returns
    -------
    A : ndarray, shape (n_rows, n_terms)
    B : ndarray, shape (n_rows, n_states)
    """
    rows_a, rows_b = [], []
    for tr in dataset:
        theta = terms.evaluate(np.concatenate([tr.x, tr.u], axis=1))
        steps = np.diff(tr.t)[:, None]
        cum = np.concatenate([np.zeros((1, theta.shape[1])), np.cumsum(0.5 * (theta[1:] + theta[:-1]) * steps, 0)])
        starts = np.arange(0, len(tr) - span, stride)
        rows_a.append(cum[starts + span] - cum[starts])
        rows_b.append(tr.x[starts + span] - tr.x[starts])
    return np.concatenate(rows_a), np.concatenate(rows_b)


def trajectory_windows(dataset: Dataset, window: int, stride: int | None = None, max_windows: int | None = None):
    """States and inputs of windows of ``window`` samples (+1 for the end point) cut from every trajectory.

    Parameters
    ----------
    stride : int, optional
        Samples between window starts (default: ``window``, i.e. back to back).
    max_windows : int, optional
        Keep at most this many, evenly spread over all trajectories and times (the cost of a
        trajectory fit is linear in the windows).

    Returns
    -------
    x : ndarray, shape (n_windows, window + 1, n_states)
    u : ndarray, shape (n_windows, window + 1, n_inputs)
    """
    stride = stride or window
    xs, us = [], []
    for tr in dataset:
        for start in range(0, len(tr) - window, stride):
            xs.append(tr.x[start:start + window + 1])
            us.append(tr.u[start:start + window + 1])
    if not xs:
        raise ValueError(f"no trajectory is longer than the window ({window} samples)")
    if max_windows is not None and len(xs) > max_windows:
        keep = np.linspace(0, len(xs) - 1, max_windows).round().astype(int)
        xs, us = [xs[k] for k in keep], [us[k] for k in keep]
    return np.array(xs), np.array(us)
