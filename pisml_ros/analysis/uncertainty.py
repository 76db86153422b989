"""How far the data pin an identified model's stability verdict.

An identified model's coefficients are estimates: the refinement's Gauss-Newton Hessian gives
their covariance for the measurement noise (:func:`covariance_metadata`, stored in the model's
``metadata["coefficient_covariance"]``), and a first-order eigenvalue perturbation carries it to
the largest real part of the eigenvalues at an operating point (:func:`max_real_std`). Where that
real part is within two standard deviations of zero, the records do not decide stability there.

The covariance counts the noise alone, not the model's own error (terms it lacks or should not
have): measured (stop 35, `make bench`, the ten 40 dB recordings' chosen models) the plant's
largest real part lay within two of these standard deviations of the model's at 47 of 68 grid
points, not the 95 % two standard deviations promise (README, "Identification benchmark"). In
ug 0.8-1.1 those models' slowest mode sits near the refinement's stability prior (-0.5 1/s at the
records' rest points: median -0.43 to -0.60 1/s at ug 0.8-1.1), not at the plant's (-0.73, -1.55,
-0.55): 40 ms records barely see it (stop 38).
"""
from __future__ import annotations

import numpy as np
import scipy.linalg

# the verdict needs the largest real part this many standard deviations from zero
VERDICT_SIGMAS = 2.0


def covariance_metadata(shape: tuple, support: np.ndarray, covariance: np.ndarray, digits: int = 6) -> dict:
    """JSON-ready covariance of the coefficients on ``support`` (flat indices into a coefficient
    matrix of ``shape`` = (n_terms, n_states)): their ``[term, state]`` entries and the packed upper
    triangle (row by row) of the matrix, rounded to ``digits`` significant digits."""
    support = np.asarray(support, dtype=int)
    cov = np.asarray(covariance, dtype=float)
    upper = cov[np.triu_indices(len(support))]
    return {"entries": [[int(k // shape[1]), int(k % shape[1])] for k in support],
            "packed_upper": [float(f"{v:.{digits}g}") for v in upper],
            "basis": "measurement noise alone (Gauss-Newton Hessian of the trajectory refinement)"}


def coefficient_covariance(model) -> tuple[np.ndarray, np.ndarray] | None:
    """``(entries, covariance)`` of an explicit model's coefficients from its metadata (entries: an
    (n, 2) array of [term, state] indices), or None where the model carries none or it does not
    fit the model's coefficient matrix (a model edited since)."""
    stored = (getattr(model, "metadata", None) or {}).get("coefficient_covariance")
    if not stored:
        return None
    entries = np.asarray(stored.get("entries") or [], dtype=int).reshape(-1, 2)
    packed = np.asarray(stored.get("packed_upper") or [], dtype=float)
    n = len(entries)
    shape = np.shape(model.coefficients)
    if n == 0 or packed.size != n * (n + 1) // 2 or entries.min() < 0 or np.any(entries.max(axis=0) >= shape) \
            or not np.all(np.isfinite(packed)):
        return None
    cov = np.zeros((n, n))
    cov[np.triu_indices(n)] = packed
    cov = cov + np.triu(cov, 1).T
    return entries, cov


def max_real_std(model, x, u, stored=None) -> float | None:
    """Standard deviation (1/s) of the largest real part of the eigenvalues of ``model``'s Jacobian
    at state ``x`` and inputs ``u``, from its coefficient covariance (first order: dλ = uᴴ dA v / uᴴv,
    the equilibrium held). None where the model carries no covariance or the eigenvalue is
    defective. ``stored``: :func:`coefficient_covariance` of the model, where the caller has it."""
    stored = coefficient_covariance(model) if stored is None else stored
    if stored is None:
        return None
    entries, cov = stored
    n = len(model.state_names)
    grad = np.asarray(model.term_gradients(x, u))[:, :n]
    d_re = max_real_slope(np.asarray(model.coefficients).T @ grad)
    if d_re is None:
        return None
    # A[j, k] = Σ_t c[t, j]·grad[t, k]: ∂A[j, :] / ∂c[t, j] = grad[t, :]
    sensitivity = np.einsum("ik,ik->i", d_re[entries[:, 1]], grad[entries[:, 0]])
    variance = float(sensitivity @ cov @ sensitivity)
    return float(np.sqrt(max(variance, 0.0)))


def max_real_slope(a: np.ndarray) -> np.ndarray | None:
    """∂Re λ / ∂A of the eigenvalue of ``a`` with the largest real part (first-order perturbation,
    dλ = uᴴ dA v / uᴴv), or None where that eigenvalue is defective."""
    lam, left, right = scipy.linalg.eig(a, left=True, right=True)
    i = int(np.argmax(lam.real))
    overlap = left[:, i].conj() @ right[:, i]
    if abs(overlap) < 1e-8:
        return None
    return np.real(np.outer(left[:, i].conj(), right[:, i]) / overlap)


def stability_verdict(max_real: float, std: float | None, sigmas: float = VERDICT_SIGMAS) -> str:
    """"stable", "unstable", or "undetermined" where ``max_real`` is within ``sigmas`` standard
    deviations of zero (without a standard deviation: the sign alone)."""
    if std is not None and abs(max_real) < sigmas * std:
        return "undetermined"
    return "stable" if max_real < 0 else "unstable"
