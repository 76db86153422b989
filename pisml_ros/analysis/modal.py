"""Modal analysis of a linearised model: eigenvalues, damping, frequencies, participation."""
from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np


@dataclasses.dataclass
class ModalSummary:
    """Eigen-structure of a state matrix A, modes ordered slowest-decaying first.

    Attributes
    ----------
    eigenvalues : ndarray of complex, 1/s
    damping : ndarray
        Damping ratio ζ = -Re(λ)/|λ| (1 for a real stable mode, negative when unstable).
    frequencies_hz : ndarray
        |Im(λ)| / 2π.
    participation : ndarray, shape (n_modes, n_states)
        Normalised participation factors |v_ik · w_ki| of each state in each mode.
    state_names : tuple of str
    """

    eigenvalues: np.ndarray
    damping: np.ndarray
    frequencies_hz: np.ndarray
    participation: np.ndarray
    state_names: tuple

    @property
    def max_real(self) -> float:
        return float(np.max(self.eigenvalues.real))

    @property
    def min_damping(self) -> float:
        return float(np.min(self.damping))

    @property
    def stable(self) -> bool:
        return self.max_real < 0.0

    def dominant_states(self, mode: int, count: int = 3) -> list[str]:
        order = np.argsort(-self.participation[mode])[:count]
        return [self.state_names[i] for i in order]

    def to_dict(self) -> dict:
        """JSON-ready summary (eigenvalues as [re, im] pairs)."""
        return {
            "eigenvalues": [[float(z.real), float(z.imag)] for z in self.eigenvalues],
            "damping": [float(d) for d in self.damping],
            "frequencies_hz": [float(f) for f in self.frequencies_hz],
            "dominant_states": [self.dominant_states(k) for k in range(len(self.eigenvalues))],
            "max_real": self.max_real,
            "min_damping": self.min_damping,
            "stable": self.stable,
        }


def damping_ratio(eigenvalues) -> np.ndarray:
    """ζ = -Re(λ)/|λ| (a zero eigenvalue counts as undamped, ζ = 0)."""
    lam = np.asarray(eigenvalues, dtype=complex)
    mag = np.abs(lam)
    return np.where(mag > 0, -lam.real / np.where(mag > 0, mag, 1.0), 0.0)


def modal_summary(a: np.ndarray, state_names: Sequence[str] | None = None) -> ModalSummary:
    """Eigenvalues, damping ratios, frequencies and participation factors of A.

    Parameters
    ----------
    a : ndarray, shape (n, n)
        State matrix (Jacobian at an equilibrium), 1/s.
    state_names : sequence of str, optional

    Returns
    -------
    ModalSummary
        Modes sorted by decreasing real part (the least stable first), conjugate
        pairs adjacent with the positive imaginary part first.
    """
    a = np.asarray(a, dtype=float)
    n = a.shape[0]
    names = tuple(state_names) if state_names is not None else tuple(f"x{k}" for k in range(n))
    eigenvalues, right = np.linalg.eig(a)
    order = np.lexsort((-eigenvalues.imag, -np.round(eigenvalues.real, 9)))
    eigenvalues, right = eigenvalues[order], right[:, order]
    try:
        left = np.linalg.inv(right)
        part = np.abs(right.T * left)  # p_ki = |v_ik w_ki|
        part = part / np.maximum(part.sum(axis=1, keepdims=True), 1e-300)
    except np.linalg.LinAlgError:  # defective matrix: participation is undefined
        part = np.full((n, n), math.nan)
    return ModalSummary(eigenvalues, damping_ratio(eigenvalues), np.abs(eigenvalues.imag) / (2 * math.pi),
                        part, names[:n] if len(names) >= n else names + tuple(f"x{k}" for k in range(len(names), n)))
