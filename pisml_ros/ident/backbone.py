"""Sparse symbolic backbone Ξ over the physics library Θ, fitted in integral (weak) form.

x(t_k+s) − x(t_k) = ∫ Θ(x, u) dt · Ξ over short windows: integrating averages the
measurement noise that derivative estimates amplify. Sparsity by pysindy's STLSQ on
normalised columns, so the threshold is relative (a fraction of each state's scale).
"""
from __future__ import annotations

import numpy as np

from ..data import Dataset
from ..data.dataset import steady_start_length
from ..model import ExplicitModel
from ..model.expressions import term_set
from .derivatives import integral_form


def sparse_regression(a: np.ndarray, b: np.ndarray, threshold: float, alpha: float,
                      max_iter: int = 20) -> np.ndarray:
    """STLSQ (pysindy) of ``b ≈ a @ c`` on unit-norm columns of both sides; returns c of shape (n_a, n_b)."""
    import pysindy as ps

    a_norm = np.linalg.norm(a, axis=0)
    a_norm = np.where(a_norm > 0, a_norm, 1.0)
    b_norm = np.linalg.norm(b, axis=0)
    b_norm = np.where(b_norm > 0, b_norm, 1.0)
    opt = ps.STLSQ(threshold=threshold, alpha=alpha, max_iter=max_iter)
    opt.fit(a / a_norm, b / b_norm)
    coef = np.atleast_2d(opt.coef_).T  # pysindy: (n_targets, n_features)
    return coef * b_norm[None, :] / a_norm[:, None]


def reference_points(dataset: Dataset, limit: int = 8) -> list[dict]:
    """Steady starts of the trajectories (mean of the pre-event samples): where equilibrium
    searches of an identified model begin (stored in the model metadata)."""
    points = []
    for tr in dataset:
        end = steady_start_length(tr)
        if end >= 3:
            points.append({"inputs": tr.u[0].tolist(), "state": tr.x[:end].mean(axis=0).tolist()})
    points.sort(key=lambda p: p["inputs"][0])
    if len(points) > limit:
        keep = np.linspace(0, len(points) - 1, limit).round().astype(int)
        points = [points[k] for k in keep]
    return points


def fit_backbone(dataset: Dataset, terms: list[str], span: int = 10, threshold: float = 0.02,
                 alpha: float = 1e-6) -> ExplicitModel:
    """Ξ over ``terms`` from ``dataset`` (integral form + STLSQ).

    Returns
    -------
    ExplicitModel
        Over the dataset's states and inputs; metadata records the method and reference points.
    """
    signals = tuple(dataset.state_names) + tuple(dataset.input_names)
    ts = term_set(terms, signals)
    a, b = integral_form(dataset, ts, span=span)
    coef = sparse_regression(a, b, threshold, alpha)
    meta = {"method": "backbone (integral-form STLSQ over Θ)", "reference_points": reference_points(dataset)}
    return ExplicitModel(dataset.state_names, dataset.input_names, terms, coef, meta)
