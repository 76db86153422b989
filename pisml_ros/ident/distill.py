"""Symbolic distillation of the neural residual and the merge with the backbone.

The trained residual N(x, u) is sampled densely over the training states and a
cloud around them, then fitted by sparse regression (pysindy STLSQ) over the
monomials of Θ_ext. Backbone and distilled terms are merged in one monomial basis
(p = v_d·i_d + v_q·i_q becomes its two monomials) so that no two columns of the
explicit model are collinear by construction.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from ..data import Dataset
from ..model import ExplicitModel
from ..model.expressions import term_set
from .backbone import sparse_regression
from .library import monomial_basis


def sample_envelope(dataset: Dataset, n_samples: int, spread: float, seed: int = 0):
    """States and inputs on and around the training envelope.

    Half the samples are measured points, half are measured points moved by
    ``spread`` × (per-signal standard deviation) in random directions.
    """
    rng = np.random.default_rng(seed)
    z = np.concatenate([np.concatenate([tr.x, tr.u], axis=1) for tr in dataset])
    pick = rng.choice(len(z), size=min(n_samples // 2, len(z)), replace=False)
    on = z[pick]
    std = z.std(axis=0)
    around = z[rng.choice(len(z), size=n_samples - len(on))]
    around = around + spread * std * rng.standard_normal(around.shape)
    both = np.concatenate([on, around])
    n_x = len(dataset.state_names)
    return both[:, :n_x], both[:, n_x:]


def distill_residual(residual: Callable, x: np.ndarray, u: np.ndarray, terms: Sequence[str],
                     signals: Sequence[str], threshold: float, alpha: float = 1e-3, max_terms: int = 6):
    """Sparse fit of ``residual(x, u)`` over the monomials of ``terms``.

    STLSQ (pysindy, ridge ``alpha`` on unit-norm columns so that collinear monomials cannot
    cancel each other with huge coefficients), then at most ``max_terms`` terms per state, those
    with the largest contribution |c|·rms(term), refitted by least squares.

    Returns
    -------
    basis : list of str
        The monomials.
    coefficients : ndarray, shape (n_basis, n_states)
    """
    basis, _ = monomial_basis(terms, signals)
    theta = term_set(basis, signals).evaluate(np.concatenate([x, u], axis=1))
    target = residual(x, u)
    coef = sparse_regression(theta, target, threshold, alpha)
    rms = np.sqrt(np.mean(theta ** 2, axis=0))
    for j in range(coef.shape[1]):
        contribution = np.abs(coef[:, j]) * rms
        keep = np.argsort(contribution)[::-1][:max_terms]
        keep = keep[contribution[keep] > 0]
        coef[:, j] = 0.0
        if keep.size:
            coef[keep, j] = np.linalg.lstsq(theta[:, keep], target[:, j], rcond=None)[0]
    return basis, coef


def merge(backbone: ExplicitModel, basis: Sequence[str], coefficients: np.ndarray, metadata: dict | None = None,
          ) -> ExplicitModel:
    """Backbone + distilled residual as one explicit model over a shared monomial basis."""
    signals = list(backbone.state_names) + list(backbone.input_names)
    back_basis, mapping = monomial_basis(backbone.terms, signals)
    back_coef = mapping.T @ backbone.coefficients  # over back_basis
    merged_terms = list(dict.fromkeys([*back_basis, *basis]))
    coef = np.zeros((len(merged_terms), backbone.n_states))
    for k, term in enumerate(back_basis):
        coef[merged_terms.index(term)] += back_coef[k]
    for k, term in enumerate(basis):
        coef[merged_terms.index(term)] += coefficients[k]
    used = np.any(coef != 0, axis=1)
    meta = dict(backbone.metadata)
    meta.update(metadata or {})
    return ExplicitModel(backbone.state_names, backbone.input_names, [t for t, keep in zip(merged_terms, used) if keep],
                         coef[used], meta)
