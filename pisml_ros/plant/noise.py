"""Per-channel measurement noise at a given signal-to-noise ratio."""
from __future__ import annotations

import numpy as np

from ..data import Dataset, Trajectory


def add_measurement_noise(dataset: Dataset, snr_db: float, seed: int = 0, include_inputs: bool = False,
                          input_snr_db: float | None = None) -> Dataset:
    """Return a copy with white Gaussian noise at ``snr_db`` on every channel.

    The noise standard deviation of a channel is its RMS over the whole dataset
    divided by 10^(snr_db/20) (40 dB: 1 % of the channel's RMS).

    Parameters
    ----------
    dataset : Dataset
    snr_db : float
    seed : int
    include_inputs : bool
        Also perturb the measured inputs (default: inputs are exact, as the
        paper's protocol applies them).
    input_snr_db : float, optional
        With ``include_inputs``: the inputs' SNR, if not ``snr_db`` (a grid voltage
        measured more precisely than the currents).

    Returns
    -------
    Dataset
        New dataset; metadata records ``snr_db`` and the per-channel noise std.
    """
    rng = np.random.default_rng(seed)
    x_all = np.concatenate([tr.x for tr in dataset.trajectories])
    sigma_x = np.sqrt(np.mean(x_all ** 2, axis=0)) / 10 ** (snr_db / 20)
    sigma_u = np.zeros(len(dataset.input_names))
    if include_inputs:
        u_all = np.concatenate([tr.u for tr in dataset.trajectories])
        sigma_u = np.sqrt(np.mean(u_all ** 2, axis=0)) / 10 ** ((snr_db if input_snr_db is None else input_snr_db) / 20)
    noisy = [
        Trajectory(tr.traj_id, tr.t.copy(), tr.x + rng.standard_normal(tr.x.shape) * sigma_x,
                   tr.u + rng.standard_normal(tr.u.shape) * sigma_u)
        for tr in dataset.trajectories
    ]
    meta = dict(dataset.metadata)
    meta.update(snr_db=float(snr_db), noise_seed=int(seed),
                noise_std=dict(zip(dataset.state_names + dataset.input_names,
                                   np.concatenate([sigma_x, sigma_u]).tolist())))
    return Dataset(dataset.state_names, dataset.input_names, noisy, meta)
