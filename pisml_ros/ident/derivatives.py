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


def integral_form(dataset: Dataset, terms: TermSet, span: int = 10, stride: int = 1,
                  quadrature: str = "trapezoid"):
    """Integral (weak) form of dx/dt = Θ(x, u) C over windows of ``span`` samples.

    x(t_{k+span}) - x(t_k) = ∫ Θ dt · C: a linear least-squares problem A C = B that, unlike
    derivatives, averages the noise.

    Parameters
    ----------
    quadrature : {"trapezoid", "spline"}
        How ∫ Θ dt is computed from the samples: the trapezoid rule, or the integral of the cubic
        interpolating spline (scipy), in pieces between input jumps, the windows in which an input
        jumps dropped (no quadrature of the samples integrates a step that falls between them).
        On clean protocol data the true equations then fit to ~1e-4 (slow rows) and ~1e-2 (LCL
        rows) of the increments, where the trapezoid rule leaves 7-9 % in the LCL rows (~6 samples
        per LCL period).

    Returns
    -------
    A : ndarray, shape (n_rows, n_terms)
    B : ndarray, shape (n_rows, n_states)
    """
    if quadrature not in ("trapezoid", "spline"):
        raise ValueError(f"quadrature must be 'trapezoid' or 'spline', got {quadrature!r}")
    rows_a, rows_b = [], []
    for tr in dataset:
        theta = terms.evaluate(np.concatenate([tr.x, tr.u], axis=1))
        starts = np.arange(0, len(tr) - span, stride)
        if quadrature == "spline":
            # piece k runs from one input jump to the next; each restarts its integral at 0
            piece = np.concatenate([[0], np.cumsum(input_jumps(tr.u))])
            cum = np.concatenate([cumulative_integral(theta[piece == k], tr.t[piece == k], quadrature)
                                  for k in range(piece[-1] + 1)])
            starts = starts[piece[starts + span] == piece[starts]]
        else:
            cum = cumulative_integral(theta, tr.t, quadrature)
        rows_a.append(cum[starts + span] - cum[starts])
        rows_b.append(tr.x[starts + span] - tr.x[starts])
    return np.concatenate(rows_a), np.concatenate(rows_b)


def input_jumps(u: np.ndarray, factor: float = 20.0) -> np.ndarray:
    """Which sample intervals hold an input jump: a change of some input larger than ``factor``
    times its median change (any change, for piecewise-constant inputs); shape (len(u) - 1,)."""
    change = np.abs(np.diff(u, axis=0))
    if change.size == 0:
        return np.zeros(0, dtype=bool)
    typical = np.median(change, axis=0)
    return np.any(change > np.maximum(factor * typical, 1e-12 * (1 + np.abs(u).max(axis=0))), axis=1)


def cumulative_integral(values: np.ndarray, t: np.ndarray, quadrature: str = "trapezoid") -> np.ndarray:
    """∫ from t[0] to each t of ``values`` (rows at the times ``t``), by the trapezoid rule or the
    cubic interpolating spline (``quadrature`` as :func:`integral_form`'s)."""
    if len(t) > 3 and quadrature == "spline":
        from scipy.interpolate import make_interp_spline

        antiderivative = make_interp_spline(t, values, k=3, axis=0).antiderivative()
        return antiderivative(t) - antiderivative(t[0])
    steps = np.diff(t)[:, None]
    return np.concatenate([np.zeros((1, values.shape[1])), np.cumsum(0.5 * (values[1:] + values[:-1]) * steps, 0)])


def window_starts(dataset: Dataset, window: int, stride: int | None = None,
                  max_windows: int | None = None) -> list:
    """``(trajectory index, first sample)`` of every window of ``window`` samples (+1 for the end
    point) cut from every trajectory, ``stride`` samples apart (default: back to back), evenly thinned
    to at most ``max_windows``: the windows of :func:`trajectory_windows` and :func:`rest_window_starts`."""
    stride = stride or window
    starts = [(k, start) for k, tr in enumerate(dataset) for start in range(0, len(tr) - window, stride)]
    if max_windows is not None and len(starts) > max_windows:
        keep = np.linspace(0, len(starts) - 1, max_windows).round().astype(int)
        starts = [starts[k] for k in keep]
    return starts


def rest_window_starts(dataset: Dataset, window: int, stride: int | None = None, max_windows: int | None = None):
    """For each window of :func:`trajectory_windows` (the same order and thinning): where the whole
    window lies inside its trajectory's steady start (the record sat at rest), that rest's mean state
    (:func:`~pisml_ros.data.dataset.steady_start_mean`) and its number of samples; NaN and 0 elsewhere.

    Returns
    -------
    targets : ndarray, shape (n_windows, n_states)
    samples : ndarray, shape (n_windows,)
    """
    from ..data.dataset import steady_start_mean

    rests = [steady_start_mean(tr) for tr in dataset]
    starts = window_starts(dataset, window, stride, max_windows)
    targets = np.full((len(starts), len(dataset.state_names)), np.nan)
    samples = np.zeros(len(starts))
    for row, (k, start) in enumerate(starts):
        end, rest = rests[k]
        if rest is not None and start + window < end:  # samples start ... start + window
            targets[row], samples[row] = rest, end
    return targets, samples


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
    starts = window_starts(dataset, window, stride, max_windows)
    if not starts:
        raise ValueError(f"no trajectory is longer than the window ({window} samples)")
    trajectories = dataset.trajectories
    return (np.array([trajectories[k].x[start:start + window + 1] for k, start in starts]),
            np.array([trajectories[k].u[start:start + window + 1] for k, start in starts]))
