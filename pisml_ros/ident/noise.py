"""Noise level of measured channels, estimated from the data itself."""
from __future__ import annotations

import numpy as np

from ..data import Dataset
from ..data.dataset import rest_start_length


def estimate_noise_std(dataset: Dataset, min_samples: int = 8) -> np.ndarray:
    """Per-state noise standard deviation.

    Where a trajectory starts at rest (:func:`~pisml_ros.data.dataset.rest_start_length`:
    inputs constant and the states still), the first differences there are pure noise:
    σ = std(Δx)/√2. Without such a segment, the second difference bounds it from above:
    σ ≈ std(Δ²x)/√6.

    Returns
    -------
    ndarray, shape (n_states,)
    """
    flat_diffs = []
    for tr in dataset:
        end = rest_start_length(tr)
        if end >= min_samples:
            flat_diffs.append(np.diff(tr.x[:end], axis=0))
    if flat_diffs:
        d = np.concatenate(flat_diffs)
        # the slow drift of a not-quite-steady start is removed by the median of the differences
        return np.std(d - np.median(d, axis=0), axis=0) / np.sqrt(2.0)
    d2 = np.concatenate([np.diff(tr.x, n=2, axis=0) for tr in dataset if len(tr) > 2])
    return np.std(d2, axis=0) / np.sqrt(6.0)


def residual_weights(dataset: Dataset) -> np.ndarray:
    """Trajectory-residual weight per state: 1 / the measured noise std, the std floored at 1e-4 of
    the state's spread over the records (clean records: no infinite weights).

    Returns
    -------
    ndarray, shape (n_states,)
    """
    spread = np.concatenate([tr.x for tr in dataset]).std(axis=0)
    return 1.0 / np.maximum(estimate_noise_std(dataset), 1e-4 * spread + 1e-12)


def noise_floor_error(dataset: Dataset) -> float:
    """The training error (``analysis.metrics.relative_error``, averaged over the records, %) that
    the noise alone leaves: what a model reproducing the noise-free states exactly would score
    against these noisy records, ‖noise‖ ≈ σ·√n for each state of each record.

    Returns
    -------
    float
        Near 0 on clean records; about 1.5-2.0 % on the protocol's 40 dB training and small-signal
        records, 2.7-2.9 % with the small-signal steps at ug 1.0 (all 13 states, σ from
        :func:`estimate_noise_std`).
    """
    sigma = estimate_noise_std(dataset)
    floors = [np.mean(sigma * np.sqrt(len(tr)) / np.maximum(np.linalg.norm(tr.x, axis=0), 1e-12)) * 100
              for tr in dataset]
    return float(np.mean(floors))
