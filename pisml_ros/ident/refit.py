"""Sparse re-fit of the whole field on the data, in equation-error (integral) form.

The merged explicit model (backbone + distilled residual) takes its coefficients from two
separate fits (the backbone's regression, the residual's distillation), and the distillation
keeps at most a few terms per state. Here every term of a library (PISML uses the monomials of
Θ and Θ_ext: what the backbone and the distillation search) is fitted jointly to the measured
increments x(t+s) − x(t) = ∫Θ dt · C (cubic-spline quadrature, windows across input jumps
dropped), then each state's row is made sparse by backward elimination on its exact
least-squares cost (:func:`least_squares_elimination`): the spurious members of a near-collinear
group go one at a time, which a one-shot threshold cannot do.

Measured on the clean protocol recordings (the 54 monomials of Θ ∪ Θ_ext): within +1000 % of
each row's least-squares cost, 72 nonzero coefficients against the truth's 88, none spurious; the
Pf and Qf rows exactly the true ones, with the Rd current×current products; missing: eight
(il − ig) pairs of the controller's cross-couplings (the small capacitor current, nearly
collinear with the vc terms at these operating points). IOD/OOD 0.010/0.015 %, in 0.2 s. On an
inverter with a small filter capacitor (bench/plants_bench.py's vendor-c) 71 coefficients, where
the elimination on the normal equations kept 194 (see :func:`least_squares_elimination`). With
measurement noise the equation error is biased (noise in the regressors) and these candidates
lose the selection to the trajectory-fitted ones (60 dB: ~4.5 % training error; 100 dB: some drop
integrator terms and lose their equilibrium).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..data import Dataset
from ..model.expressions import term_set
from .derivatives import integral_form


def sparse_refit(dataset: Dataset, terms: Sequence[str], budgets: Sequence[float], span: int = 10
                 ) -> list[np.ndarray]:
    """Coefficient matrices over ``terms`` fitted to ``dataset``, one per budget.

    Parameters
    ----------
    dataset : Dataset
    terms : sequence of str
        Term strings over the dataset's state and input names.
    budgets : sequence of float
        Allowed rise of each row's equation-error cost over its least-squares minimum on all
        ``terms`` (relative: 1.0 lets it double); larger budgets give sparser models.
    span : int
        Samples per integral-form window.

    Returns
    -------
    list of ndarray, shape (n_terms, n_states)
        In the order of ``budgets``.

    Raises
    ------
    ValueError
        When the records hold fewer windows of ``span`` samples free of input jumps than terms.
    """
    signals = tuple(dataset.state_names) + tuple(dataset.input_names)
    a, b = integral_form(dataset, term_set(list(terms), signals), span=span, quadrature="spline")
    if a.shape[0] <= a.shape[1]:
        raise ValueError(f"sparse re-fit: {a.shape[0]} windows of {span} samples without an input jump for "
                         f"{a.shape[1]} terms; the records are too short")
    # one orthogonal reduction for every row: ‖a·c − b_j‖² = ‖r·c − rb_j‖² + the part of b_j outside a's range
    r_all = np.linalg.qr(np.hstack([a, b]), mode="r")
    n = a.shape[1]
    r, rb, outside = r_all[:n, :n], r_all[:n, n:], (r_all[n:, n:] ** 2).sum(axis=0)
    out = [np.zeros((n, b.shape[1])) for _ in budgets]
    for j in range(b.shape[1]):
        least = 0.5 * (_least_squares(r, rb[:, j])[1] + outside[j])
        for k, row in enumerate(least_squares_elimination(r, rb[:, j], [budget * least for budget in budgets])):
            out[k][:, j] = row
    return out


def least_squares_elimination(a: np.ndarray, b: np.ndarray, budgets: Sequence[float]) -> list[np.ndarray]:
    """Sparser least-squares fits of ``a @ c ≈ b`` by greedy backward elimination.

    Repeatedly drops the column whose removal (the others re-fitted) raises the cost ½‖a·c − b‖²
    least, down to one column, and returns for each budget the sparsest fit on that path whose
    cost exceeds the full least-squares cost by at most the budget.

    Why not :func:`~pisml_ros.ident.trajfit.backward_elimination` on the normal equations: aᵀa
    squares the condition number of ``a``, and on clean records the equation error left by the
    true terms is ~1e-14 of the increments' energy. A plant with a small filter capacitor (the
    grid and filter currents nearly equal) gave cond(a) 2.4e6, so the inverse of aᵀa was too
    imprecise to rank the removals: the δ row kept 13 of 54 terms where the true 2 cost 1.3× the
    least-squares cost. Here every step re-fits from ``a``'s singular value decomposition (a
    precision of cond(a), not its square), and the rises are costs, not a quadratic model's.

    Parameters
    ----------
    a : ndarray, shape (m, n)
        Regressors (a triangular factor of them will do: only ‖a·c − b‖ matters).
    b : ndarray, shape (m,)
    budgets : sequence of float
        Allowed rises of the cost over its least-squares minimum (absolute).

    Returns
    -------
    list of ndarray, shape (n,)
        One coefficient vector per budget, zero off its support.
    """
    scale = np.linalg.norm(a, axis=0)
    scale[scale == 0] = 1.0
    a = a / scale  # the removal ranking is invariant to column scaling; the SVD's cut-off is not
    live = np.ones(a.shape[1], dtype=bool)
    coef, full_cost, inverse_diag = _least_squares(a, b, with_inverse_diagonal=True)
    path = [(0.0, np.flatnonzero(live), coef)]
    while live.sum() > 1:
        columns = np.flatnonzero(live)
        # the rise from dropping column k, the others re-fitted: c_k² / (aᵀa)⁻¹_kk (exact for least
        # squares); a column outside the numerical range carries nothing (c_k = 0): it goes first
        rises = np.where(inverse_diag > 0, coef ** 2 / np.maximum(inverse_diag, 1e-300), 0.0)
        live[columns[int(np.argmin(rises))]] = False
        columns = np.flatnonzero(live)
        coef, cost, inverse_diag = _least_squares(a[:, columns], b, with_inverse_diagonal=True)
        path.append((0.5 * (cost - full_cost), columns, coef))
    out = []
    for budget in budgets:
        _, columns, coef = min((p for p in path if p[0] <= budget), key=lambda p: (p[1].size, p[0]))
        full = np.zeros(a.shape[1])
        full[columns] = coef / scale[columns]
        out.append(full)
    return out


def _least_squares(a, b, with_inverse_diagonal=False):
    """Minimum-norm least squares by SVD: (coefficients, ‖a·c − b‖², diag((aᵀa)⁺) if asked)."""
    u, s, vt = np.linalg.svd(a, full_matrices=False)
    keep = s > s[0] * max(a.shape) * np.finfo(float).eps
    coef = vt[keep].T @ ((u[:, keep].T @ b) / s[keep])
    cost = float(((a @ coef - b) ** 2).sum())
    if not with_inverse_diagonal:
        return coef, cost
    return coef, cost, ((vt[keep] / s[keep, None]) ** 2).sum(axis=0)
