"""Sparse re-fit of the whole field on the data, in equation-error (integral) form.

The merged explicit model (backbone + distilled residual) takes its coefficients from two
separate fits (the backbone's regression, the residual's distillation), and the distillation
keeps at most a few terms per state. Here every term of a library (PISML uses the monomials of
Θ and Θ_ext: what the backbone and the distillation search) is fitted jointly to the measured
increments x(t+s) − x(t) = ∫Θ dt · C (cubic-spline quadrature, windows across input jumps
dropped), then each state's row is made sparse by backward elimination on its exact quadratic
cost (:func:`~pisml_ros.ident.trajfit.backward_elimination`): the spurious members of a
near-collinear group go one at a time, which a one-shot threshold cannot do.

Measured on the clean protocol recordings (the 54 monomials of Θ ∪ Θ_ext): within +1000 % of
each row's least-squares cost, 72 nonzero coefficients against the truth's 88, none spurious; the
Pf and Qf rows exactly the true ones, with the Rd current×current products; missing: eight
(il − ig) pairs of the controller's cross-couplings (the small capacitor current, nearly
collinear with the vc terms at these operating points). IOD/OOD 0.010/0.015 %, in 0.1 s. With measurement noise the equation error is biased (noise in
the regressors) and these candidates lose the selection to the trajectory-fitted ones (60 dB:
~4.5 % training error; 100 dB: some drop integrator terms and lose their equilibrium).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..data import Dataset
from ..model.expressions import term_set
from .derivatives import integral_form
from .trajfit import backward_elimination


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
    full = np.linalg.lstsq(a, b, rcond=None)[0]
    row_cost = 0.5 * ((a @ full - b) ** 2).sum(axis=0)
    hessian = a.T @ a  # of every row's cost: rows share the regressors
    support = np.arange(len(terms))
    out = [np.zeros_like(full) for _ in budgets]
    for j in range(b.shape[1]):
        for k, (_, row) in enumerate(backward_elimination(full[:, j:j + 1], hessian, support,
                                                          [budget * row_cost[j] for budget in budgets])):
            out[k][:, j] = row[:, 0]
    return out
