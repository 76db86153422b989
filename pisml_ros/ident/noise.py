"""Noise level of measured channels, estimated from the data itself."""
from __future__ import annotations

import numpy as np

from ..data import Dataset, Trajectory
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


def estimated_snr_db(dataset: Dataset) -> float:
    """The records' signal-to-noise ratio (dB), estimated: per state, its RMS over all the records
    against its noise standard deviation (:func:`estimate_noise_std`), 20·log10(RMS / σ); the median
    over the states (a state whose σ estimate is off, or whose RMS is near zero, does not move it).

    Unlike :func:`noise_floor_error`, which weighs each record by its own norm, it does not move with
    the operating points the records visit (stop 96: the protocol's training records and those of
    every scenario of ``bench/scenarios_bench.py`` tried give 39.8-40.1 dB at 40 dB and 34.9-35.1 dB
    at 35 dB, where the noise floor of records starting at ug 0.6-1.0 reaches 2.5 % at 40 dB, above the
    protocol's 2.1 % at 35 dB).

    Returns
    -------
    float
        inf on clean records (σ = 0 on every state).
    """
    sigma = estimate_noise_std(dataset)
    x = np.concatenate([tr.x for tr in dataset])
    rms = np.sqrt(np.mean(x ** 2, axis=0))
    # (a noise-free state: inf; a state at zero throughout, with noise: -inf)
    ratio = np.where(sigma > 0, rms / np.where(sigma > 0, sigma, 1.0), np.inf)
    with np.errstate(divide="ignore"):
        return float(np.median(20.0 * np.log10(ratio)))


def input_noise_std(dataset: Dataset) -> np.ndarray:
    """Per-input noise standard deviation of the measured inputs, from their second differences.

    σ = 1.4826·MAD(Δ²u)/√6 (the median absolute deviation, so that the steps of a grid test,
    which touch two second differences each, do not count): exactly 0 for inputs applied as exact
    steps (the virtual HIL's), the noise level for measured ones.

    Returns
    -------
    ndarray, shape (n_inputs,)
    """
    d2 = [np.diff(tr.u, n=2, axis=0) for tr in dataset if len(tr) > 2]
    if not d2:
        return np.zeros(len(dataset.input_names))
    d2 = np.concatenate(d2)
    return 1.4826 * np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) / np.sqrt(6.0)


def _best_interval(u: np.ndarray, sigma: float, min_samples: int) -> tuple:
    """The inner interval [i, j) of ``u`` (0 < i < j < len(u)) whose mean differs most from the
    rest's, in standard errors at noise ``sigma``: (statistic, i, j), statistic 0 where none fits."""
    n = len(u)
    cum = np.concatenate([[0.0], np.cumsum(u)])
    best = (0.0, 0, 0)
    for i in range(1, n - min_samples):
        # at least min_samples inside and outside, and the interval's end before the stretch's
        j = np.arange(i + min_samples, min(n, n - min_samples + i + 1))
        if not j.size:
            continue
        size = j - i
        inside = cum[j] - cum[i]
        shift = np.abs(inside / size - (cum[-1] - inside) / (n - size))
        statistic = shift / (sigma * np.sqrt(1.0 / size + 1.0 / (n - size)))
        k = int(np.argmax(statistic))
        if statistic[k] > best[0]:
            best = (float(statistic[k]), i, int(j[k]))
    return best


def _mean_shift_segments(u: np.ndarray, sigma: float, threshold: float, interval_threshold: float = 0.0,
                         min_samples: int = 8) -> list:
    """Binary segmentation of one input channel into stretches of constant mean: a stretch is split
    where the two sides' means differ most, in standard errors at noise ``sigma``, while that
    exceeds ``threshold``; where no single split does, an inner interval of at least ``min_samples``
    whose mean differs from the rest's by more than ``interval_threshold`` (0: not tested) splits it in
    three (circular binary segmentation's test: a shallow sag and its recovery, which one split
    sees diluted; stop 92, recordings 240-247 and 280-287: 8 of 577 steps missed). Returns the
    stretches' (start, end) sample indices.

    Written here rather than taken from a change-point library (ruptures): with the noise level
    known the test is a few lines, and there is no rosdep key for one.
    """
    stretches, pending = [], [(0, len(u))]
    while pending:
        a, b = pending.pop()
        n = b - a
        if n < 2:
            stretches.append((a, b))
            continue
        cum = np.cumsum(u[a:b])
        k = np.arange(1, n)
        left = cum[:-1] / k
        right = (cum[-1] - cum[:-1]) / (n - k)
        statistic = np.abs(left - right) / (sigma * np.sqrt(1.0 / k + 1.0 / (n - k)))
        best = int(np.argmax(statistic))
        if statistic[best] > threshold:
            pending += [(a, a + best + 1), (a + best + 1, b)]
            continue
        if interval_threshold > 0 and n > 2 * min_samples:
            found, i, j = _best_interval(u[a:b], sigma, min_samples)
            if found > interval_threshold:
                pending += [(a, a + i), (a + i, a + j), (a + j, b)]
                continue
        stretches.append((a, b))
    return sorted(stretches)


def _soft_edges(measured: np.ndarray, held: np.ndarray, edges: list, sigma: float, width: int) -> np.ndarray:
    """Held input ``held`` with the samples around each step between two held levels replaced by
    their posterior mean given the step's time: where a step is a few σ, the segmentation places it
    a sample or more off (stop 92: 42 of 577 steps, up to 6 samples for the small-signal records'
    1σ steps), and a step one sample off puts its whole size into that sample.

    With the two levels m1, m2 and the measured samples x_k, a step at τ (its first sample at m2)
    has log-likelihood Σ_(k<τ) ((x_k − m2)² − (x_k − m1)²) / 2σ² up to a constant; with a uniform
    prior over ``width`` samples either side (not past the middle of either stretch), sample k's mean is
    m1 + (m2 − m1)·P(τ ≤ k). A step of many σ keeps its place (P is 0 or 1 there, the levels kept
    exactly). ``edges``: (start of the stretch before, step, end of the stretch after) each.
    """
    out = held.copy()
    for before, step, after in edges:
        # not past the middle of either stretch: the next step's span starts there
        lo, hi = max((before + step) // 2, step - width), min((step + after + 1) // 2, step + width)
        m1, m2 = held[step - 1], held[step]
        x = measured[lo:hi]
        # log-likelihood of τ = lo ... hi (τ = hi: every sample of the span at m1)
        gain = np.concatenate([[0.0], np.cumsum(((x - m2) ** 2 - (x - m1) ** 2) / (2.0 * sigma ** 2))])
        weight = np.exp(gain - gain.max())
        weight /= weight.sum()
        below = np.cumsum(weight)[:-1]  # P(τ ≤ k) for k = lo ... hi − 1
        level = np.where(below > 1.0 - 1e-12, m2, np.where(below < 1e-12, m1, m1 + (m2 - m1) * below))
        out[lo:hi] = level
    return out


def _pooled_stretches(pieces: list, records: list, starts: list, sigma: float, threshold: float) -> list:
    """Which held stretches of one input share a level: groups of indices into ``pieces``.

    A grid test returns to where it was (a sag and its recovery) and its small-signal records all
    start at one operating point, so a short stretch's level is often measured far better by
    others: the 50 samples before a small-signal step hold ug to ~1e-3 p.u. at 40 dB, the 1000 of
    a record that stays there to ~2.5e-4, and the plant turns 1e-3 p.u. of ug into ~1 % of grid
    current. Stretches are pooled where their means differ by at most ``threshold`` standard errors:
    within a record, and across records only at the level every record starts at (where all agree
    on it), so that two records' unrelated levels that happen to lie close are not taken as one.

    Parameters
    ----------
    pieces : list of ndarray
        Each stretch's samples.
    records : list of int
        The record of each stretch.
    starts : list of bool
        Whether each stretch starts its record.
    sigma, threshold : float
        The input's noise; the pooling test's bound in standard errors (0: no pooling).
    """
    from scipy.cluster.hierarchy import DisjointSet

    means = np.array([p.mean() for p in pieces])
    counts = np.array([len(p) for p in pieces], dtype=float)
    sets = DisjointSet(range(len(pieces)))

    def agree(group_a, group_b):
        na, nb = counts[group_a].sum(), counts[group_b].sum()
        ma, mb = means[group_a] @ counts[group_a] / na, means[group_b] @ counts[group_b] / nb
        return abs(ma - mb) <= threshold * sigma * np.sqrt(1.0 / na + 1.0 / nb)

    def members(i):
        return sorted(sets.subset(i))

    if threshold > 0:
        first = [i for i, s in enumerate(starts) if s]
        # across records: the common start level, if every record starts on a held stretch there
        if len(first) == len(set(records)) > 1 and all(agree([i], [k for k in first if k != i]) for i in first):
            for i in first[1:]:
                sets.merge(first[0], i)
            for i in range(len(pieces)):
                if not sets.connected(i, first[0]) and agree([i], members(first[0])):
                    sets.merge(first[0], i)
        # within each record: in order of the means, each stretch joins the group before it if they agree
        for record in sorted(set(records)):
            order = sorted((i for i in range(len(pieces)) if records[i] == record), key=lambda i: means[i])
            for before, i in zip(order[:-1], order[1:]):
                if not sets.connected(before, i) and agree(members(before), members(i)):
                    sets.merge(before, i)
    return [sorted(group) for group in sets.subsets()]


def piecewise_constant_inputs(dataset: Dataset, sigma: np.ndarray | None = None, threshold: float = 6.0,
                              min_samples: int = 8, lags: int = 4, max_statistic: float = 30.0,
                              pool_threshold: float = 3.0, interval_threshold: float = 0.0, edge_width: int = 0):
    """The dataset with its noisy measured inputs replaced by their means over the stretches where
    they are constant (a grid test's sags, steps and phase jumps), found by mean-shift segmentation
    at their noise level; states untouched.

    A stretch is replaced only where the input is consistent with a constant plus white noise of
    that level: at least ``min_samples`` samples, a spread at most 1.5σ and a Box-Pierce statistic
    of its first ``lags`` autocorrelations at most ``max_statistic`` (as
    :func:`~pisml_ros.data.dataset.rest_start_length`); a ramp or an oscillation is left as
    measured. Why: the model is simulated with the measured inputs held between samples, and noise
    in them forces the fast grid-current dynamics (di_g/dt ∝ (v_c − u_g)/L_g) with what the plant
    never saw. At 40 dB on the inputs too (the protocol's recordings 0-5, stop 49) the fits with the
    inputs as measured failed (IOD 3.3-17 % or diverged), with them held 0.52-5.1 % (README, "Noise
    on the measured inputs").

    Parameters
    ----------
    dataset : Dataset
    sigma : ndarray, shape (n_inputs,), optional
        Noise standard deviation per input; default :func:`input_noise_std` of ``dataset``.
    threshold : float
        Mean shift, in standard errors, that splits a stretch (6: no split in 10 000 stretches of
        pure noise of 1000 samples, nor in 20 000 of 50 and of 400; stop 49, scratch).
    pool_threshold : float
        Stretches held at one common mean where theirs differ by at most this many standard errors
        (:func:`_pooled_stretches`: within a record, and across the records at the level they all
        start at); 0 holds each stretch at its own mean.
    interval_threshold : float
        An inner interval whose mean differs from the rest of its stretch by more than this many
        standard errors splits it where no single split does (:func:`_mean_shift_segments`; 0: off).
    edge_width : int
        Samples either side of each step between two held levels that take their posterior mean
        given the step's time (:func:`_soft_edges`; 0: the steps stay where the segmentation put them).

    Returns
    -------
    Dataset
        The dataset with the inputs replaced (its metadata records ``inputs_denoised``).
    dict
        Per input: ``sigma``, its ``rms`` and ``snr_db``, the ``stretches`` found and ``replaced``,
        the ``samples`` replaced, and how many stretches were ``pooled`` with others.
    """
    sigma = input_noise_std(dataset) if sigma is None else np.asarray(sigma, dtype=float)
    rms = np.sqrt(np.mean(np.concatenate([tr.u for tr in dataset]) ** 2, axis=0))
    report = {name: {"sigma": float(s), "rms": float(r), "snr_db": float(20 * np.log10(r / s)) if s > 0 else None,
                     "stretches": 0, "replaced": 0, "samples": 0, "pooled": 0}
              for name, s, r in zip(dataset.input_names, sigma, rms)}
    inputs = [np.array(tr.u, dtype=float) for tr in dataset]
    for j, name in enumerate(dataset.input_names):
        if not sigma[j] > 0:
            continue
        held = []  # (record, start, end) of each stretch replaced
        for r, tr in enumerate(dataset):
            for a, b in _mean_shift_segments(tr.u[:, j], sigma[j], threshold, interval_threshold, min_samples):
                report[name]["stretches"] += 1
                piece = tr.u[a:b, j]
                dev = piece - piece.mean()
                n = b - a
                if n < max(min_samples, lags + 2) or np.std(dev) > 1.5 * sigma[j]:
                    continue
                power = max(float(np.sum(dev ** 2)), 1e-300)
                whiteness = n * sum((np.sum(dev[k:] * dev[:-k]) / power) ** 2 for k in range(1, lags + 1))
                if whiteness <= max_statistic:
                    held.append((r, a, b))
                    report[name]["replaced"] += 1
                    report[name]["samples"] += n
        pieces = [dataset.trajectories[r].u[a:b, j] for r, a, b in held]
        groups = _pooled_stretches(pieces, [r for r, _, _ in held], [a == 0 for _, a, _ in held], sigma[j],
                                   pool_threshold)
        report[name]["pooled"] = sum(len(g) for g in groups if len(g) > 1)
        for group in groups:
            level = np.mean(np.concatenate([pieces[i] for i in group]))
            for i in group:
                r, a, b = held[i]
                inputs[r][a:b, j] = level
        if edge_width > 0:
            for r in sorted({r for r, _, _ in held}):
                spans = sorted((a, b) for rr, a, b in held if rr == r)
                edges = [(a0, a1, b1) for (a0, b0), (a1, b1) in zip(spans[:-1], spans[1:]) if b0 == a1]
                if edges:
                    inputs[r][:, j] = _soft_edges(dataset.trajectories[r].u[:, j], inputs[r][:, j], edges,
                                                  sigma[j], edge_width)
    trajectories = [Trajectory(tr.traj_id, tr.t, tr.x, u) for tr, u in zip(dataset, inputs)]
    meta = dict(dataset.metadata, inputs_denoised={name: r["sigma"] for name, r in report.items()})
    return Dataset(dataset.state_names, dataset.input_names, trajectories, meta), report


def noise_note(model) -> str | None:
    """What the engine made of the training records' noise, in words for a user: their estimated SNR
    (``model.metadata["training"]["estimated_snr_db"]``, :func:`estimated_snr_db`), the free-run error
    the noise alone leaves (``metadata["selection"]["noise_floor_pct"]``) and whether they counted as
    low-SNR (a ``metadata["low_snr_pass"]`` record, ``IdentConfig.low_snr_below_db``) and how many neural
    residuals were refined (``metadata["residual_fits"]``, ``IdentConfig.residual_fits``); None on clean
    records."""
    metadata = getattr(model, "metadata", None) or {}
    snr = (metadata.get("training") or {}).get("estimated_snr_db")
    if snr is None:
        return None
    floor = (metadata.get("selection") or {}).get("noise_floor_pct")
    low = metadata.get("low_snr_pass")
    residuals = metadata.get("residual_fits") or []
    return (f"records' estimated SNR {snr:.1f} dB"
            + (f" (the noise alone leaves {floor:.3g} % free-run error)" if floor is not None else "")
            + (f"; low-SNR: a second refinement pass in windows of {', '.join(map(str, low['windows']))} "
               f"samples (candidates \"...{low['suffix']}\")" if low else "")
            + (f"; {1 + len(residuals)} neural residuals, each refined from its own start (candidates "
               + ", ".join(f'"...{record["suffix"]}"' for record in residuals) + ")" if residuals else ""))
