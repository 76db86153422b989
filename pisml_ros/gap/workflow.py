"""The gap workflow: where do reference and measurement disagree, which named effect explains it,
how much does adding it shrink the gap.

1. **Where**: replay the measured inputs through the reference from each trajectory's
   measured initial state; per-state residuals normalised by the noise level estimated
   from the data; windows where the smoothed residual leaves the noise band.
2. **Name**: fit every catalogue candidate (screening on a grid, then scipy
   ``least_squares`` for the most promising), rank by BIC, accept the winner when the
   evidence is strong; repeat greedily for a second or third effect. When no candidate
   explains the residual, learn it by sparse regression over Θ_ext (``unnamed``).
3. **Add and show**: the augmented reference, the gap before and after, overall and per window.
"""
from __future__ import annotations

import dataclasses
import inspect
import math
import time

import numpy as np
import scipy.optimize

from ..data import Dataset
from ..data.dataset import rest_start_length
from ..ident.noise import estimate_noise_std, input_noise_std, piecewise_constant_inputs
from ..signals import SCORED_STATES
from .catalogue import Candidate, catalogue
from .lockstep import Lockstep, LockstepMap, current_call
from .reference import simulate_references


# relative step of the finite-difference probe that screens a drift or mismatch candidate
_GAUSS_NEWTON_STEP = 0.05
# scipy >= 1.16 evaluates a finite-difference Jacobian's columns through a map (`workers`): then they
# share one stacked simulation; older scipy (a ROS distribution's python3-scipy) evaluates them in turn
_LEAST_SQUARES_MAP = "workers" in inspect.signature(scipy.optimize.least_squares).parameters


@dataclasses.dataclass
class GapSettings:
    """Knobs of the workflow (defaults suit the paper's 10 kHz protocol data)."""

    smooth: int = 10            # samples of the moving average in the detector
    threshold: float = 5.0      # detector threshold, in standard deviations of the smoothed noise
    min_window: int = 5         # samples a window must last
    merge_gap: int = 20         # windows closer than this (samples) are merged
    sim_floor: float = 1e-3     # simulation accuracy (RK4, 2 substeps), relative to the channel RMS
    chi2_done: float = 3.0      # whitened SSE per residual below which the data is explained
    screen_points: int = 3
    refine_top: int = 4
    max_nfev: int = 12
    max_effects: int = 3
    min_delta_bic: float = 20.0
    min_reduction: float = 0.2  # an effect must remove at least this fraction of the whitened SSE
    min_relative_change: float = 0.02  # drift/mismatch below 2 % of nameplate is tolerance, not an effect
    substeps: int = 2
    # noisy measured inputs held at their means where they are constant before the replay
    # (ident.noise.piecewise_constant_inputs; exact inputs untouched), each held level corrected
    # within its σ/√n like the starts: replayed as measured, 40 dB on ug and theta_g made the
    # nominal plant "disagree" with its own records (stop 49)
    hold_noisy_inputs: bool = True


def initial_states(data: Dataset) -> tuple[list[np.ndarray], np.ndarray]:
    """Measured initial state of each trajectory: the mean of its steady start where it sat at rest
    there (:func:`~pisml_ros.data.dataset.rest_start_length`), else its first sample.

    Returns the states and, per trajectory, how many samples were averaged.
    """
    out, counts = [], []
    for tr in data:
        k0 = rest_start_length(tr)
        count = min(k0, 20) if k0 else 1
        out.append(tr.x[:count].mean(axis=0))
        counts.append(count)
    return out, np.array(counts, dtype=float)


def _held_stretches(u: np.ndarray, sigma_u: np.ndarray) -> list:
    """(input column, start, end, prior σ/√n) of each stretch of ``u`` held at one value (the
    stretches :func:`~pisml_ros.ident.noise.piecewise_constant_inputs` replaced by their means: in
    a column with noise, nothing else repeats a value)."""
    out = []
    for column in np.flatnonzero(sigma_u > 0):
        edges = [0, *(np.flatnonzero(np.diff(u[:, column]) != 0) + 1).tolist(), len(u)]
        out += [(int(column), a, b, float(sigma_u[column] / np.sqrt(b - a)))
                for a, b in zip(edges[:-1], edges[1:]) if b - a > 1]
    return out


def _with_starts(data: Dataset, starts) -> Dataset:
    """A copy whose first samples are the estimated initial states (only the simulation start uses them)."""
    trajs = []
    for tr, x0 in zip(data, starts):
        x = tr.x.copy()
        x[0] = x0
        trajs.append(dataclasses.replace(tr, x=x))
    return Dataset(data.state_names, data.input_names, trajs, dict(data.metadata))


def gap_percent(data: Dataset, preds, rows=None) -> float:
    """Relative L2 error (%) over the scored states, averaged over them (all trajectories pooled).

    ``rows``: optional list of (traj index, slice) to restrict to windows.
    """
    cols = data.state_index([s for s in SCORED_STATES if s in data.state_names])
    rows = rows if rows is not None else [(k, slice(None)) for k in range(len(data))]
    errs = []
    for c in cols:
        num = sum(float(np.sum((preds[k][sl, c] - data.trajectories[k].x[sl, c]) ** 2)) for k, sl in rows)
        den = sum(float(np.sum(data.trajectories[k].x[sl, c] ** 2)) for k, sl in rows)
        errs.append(math.sqrt(num / den) * 100 if den > 0 and math.isfinite(num) else math.inf)
    return float(np.mean(errs))


class GapWorkflow:
    """Run the gap workflow against a reference (:class:`PlantReference` or :class:`ModelReference`)."""

    def __init__(self, reference, settings: GapSettings | None = None, log=None):
        self.reference = reference
        self.settings = settings or GapSettings()
        self.log = log or (lambda text: None)

    # ------------------------------------------------------------------ residuals
    def _prepare(self, data: Dataset):
        self.inputs_denoised = {}
        self.held_stretches = [[] for _ in data]
        sigma_u = input_noise_std(data)
        if self.settings.hold_noisy_inputs and np.any(sigma_u > 0):
            data, self.inputs_denoised = piecewise_constant_inputs(data, sigma=sigma_u)
            self.held_stretches = [_held_stretches(tr.u, sigma_u) for tr in data]
        noise = estimate_noise_std(data)
        x_all = np.concatenate([tr.x for tr in data])
        rms = np.sqrt(np.mean(x_all ** 2, axis=0))
        self.noise = noise
        self.sigma = np.sqrt(noise ** 2 + (self.settings.sim_floor * rms) ** 2) + 1e-12
        self.data = data
        starts, counts = initial_states(data)
        self.start_sigma = noise[None, :] / np.sqrt(counts)[:, None] + 1e-12 * (rms[None, :] + 1e-12)
        self.sim_data = _with_starts(data, starts)

    def start_sensitivities(self, ref) -> None:
        """Sensitivity of each simulated trajectory to its start, within the start's noise.

        A start averaged from noisy samples is still off by σ/√k; in the slow states
        (angle, filtered power, integrators) that offset persists and grows over the
        record and would read as a model gap. Every residual below is therefore taken
        after the best start correction δ under the prior N(0, σ²/k), linearised with
        these sensitivities (one Gauss-Newton step of the start: variable projection).
        The prior keeps the correction from absorbing a real effect. Inputs held at a stretch's
        mean (``hold_noisy_inputs``) are corrected the same way, each level within σ_u/√n.
        """
        data, n_states = self.sim_data, len(self.data.state_names)
        trajs, sizes = [], []
        for k, tr in enumerate(data):
            for j in range(-1, n_states):
                x = tr.x.copy()
                if j >= 0:
                    x[0, j] += self.start_sigma[k, j]
                trajs.append(dataclasses.replace(tr, x=x))
            # inputs held at a stretch's mean are off by their prior σ/√n as well (hold_noisy_inputs)
            for column, a, b, prior in self.held_stretches[k]:
                u = tr.u.copy()
                u[a:b, column] += prior
                trajs.append(dataclasses.replace(tr, u=u))
            sizes.append(n_states + 1 + len(self.held_stretches[k]))
        preds = ref.simulate(Dataset(data.state_names, data.input_names, trajs, dict(data.metadata)),
                             substeps=self.settings.substeps)
        self.start_jac = []
        for k, first in enumerate(np.cumsum([0, *sizes[:-1]])):
            block = preds[first:first + sizes[k]]
            jac = np.stack([((p - block[0]) / self.sigma).ravel() for p in block[1:]], axis=1)
            jac = np.where(np.isfinite(jac), jac, 0.0)
            self.start_jac.append((jac, np.linalg.inv(jac.T @ jac + np.eye(jac.shape[1])) @ jac.T))

    def corrected(self, preds, traj_index=None) -> list[np.ndarray]:
        """Predictions after the best start correction of each trajectory (see start_sensitivities)."""
        traj_index = list(traj_index if traj_index is not None else range(len(preds)))
        out = []
        for p, k in zip(preds, traj_index):
            r = ((self.data.trajectories[k].x - p) / self.sigma).ravel()
            if not np.all(np.isfinite(r)):
                out.append(p)
                continue
            jac, solve = self.start_jac[k]
            out.append(p + (jac @ (solve @ r)).reshape(p.shape) * self.sigma)
        return out

    def _whitened(self, preds, traj_index) -> np.ndarray:
        preds = self.corrected(preds, traj_index)
        res = [((preds[i] - self.data.trajectories[k].x) / self.sigma).ravel() for i, k in enumerate(traj_index)]
        r = np.concatenate(res)
        return np.where(np.isfinite(r), r, 1e3)

    def _substeps(self, coarse: bool) -> int:
        # screening only ranks candidates: one RK4 step per sample is accurate enough there
        return max(1, self.settings.substeps // 2) if coarse else self.settings.substeps

    def _simulate(self, ref, traj_index=None, coarse: bool = False):
        return ref.simulate(self.sim_data, substeps=self._substeps(coarse), traj_index=traj_index)

    def _simulate_all(self, refs, traj_index=None, coarse: bool = False):
        """:meth:`_simulate` of several references in one vectorised pass (the same numbers)."""
        return simulate_references(refs, self.sim_data, substeps=self._substeps(coarse), traj_index=traj_index)

    def detect(self, preds) -> list[dict]:
        """Windows where the smoothed normalised residual leaves the noise band."""
        s = self.settings
        windows = []
        kernel = np.ones(s.smooth) / s.smooth
        limit = s.threshold / math.sqrt(s.smooth)
        for k, tr in enumerate(self.data):
            e = (tr.x - preds[k]) / self.sigma
            e = np.where(np.isfinite(e), e, 1e3)
            smooth = np.stack([np.convolve(e[:, j], kernel, mode="same") for j in range(e.shape[1])], axis=1)
            flagged = np.abs(smooth) > limit
            any_flag = flagged.any(axis=1)
            runs = _runs(any_flag, s.min_window, s.merge_gap)
            for a, b in runs:
                first = [int(np.argmax(flagged[a:b + 1, j])) if flagged[a:b + 1, j].any() else None
                         for j in range(e.shape[1])]
                order = sorted((f, j) for j, f in enumerate(first) if f is not None)
                states = [self.data.state_names[j] for _, j in order]
                windows.append({"traj": int(tr.traj_id), "traj_index": k, "i0": int(a), "i1": int(b),
                                "t0": float(tr.t[a]), "t1": float(tr.t[b]), "states": states,
                                "max_z": float(np.abs(smooth[a:b + 1]).max() * math.sqrt(s.smooth)),
                                "conditions": self._conditions(k, a, b)})
        return windows

    def _conditions(self, k, a, b) -> dict:
        tr = self.data.trajectories[k]
        cond = {}
        if "ug" in self.data.input_names:
            ug = tr.u[a:b + 1, self.data.input_names.index("ug")]
            cond["ug_min"], cond["ug_max"] = float(ug.min()), float(ug.max())
        sig = self.reference.internal_signals(tr.x[a:b + 1], tr.u[a:b + 1])
        if "ilref_unlimited_d" in sig:
            cond["ilref_max"] = float(np.hypot(sig["ilref_unlimited_d"], sig["ilref_unlimited_q"]).max())
        if "w" in sig:
            cond["w_min"], cond["w_max"] = float(np.min(sig["w"])), float(np.max(sig["w"]))
        if "vi_cmd_d" in sig:
            cond["vi_max"] = float(np.hypot(sig["vi_cmd_d"], sig["vi_cmd_q"]).max())
        names = self.data.state_names
        if "ig_d" in names and "ig_q" in names:
            ig = tr.x[a:b + 1][:, [names.index("ig_d"), names.index("ig_q")]]
            cond["ig_max"] = float(np.hypot(ig[:, 0], ig[:, 1]).max())
        return cond

    # ------------------------------------------------------------------ fitting
    def _bic(self, sse, n, k):
        return n * math.log(max(sse, 1e-300) / n) + k * math.log(n)

    def _simulate_here(self, ref, traj_index):
        """:meth:`_simulate`, joined with the other tasks' where this thread runs in a lockstep."""
        call = current_call()
        if call is None:
            return self._simulate(ref, traj_index)
        return call((ref, None if traj_index is None else tuple(traj_index)))

    def _simulate_items(self, items):
        """:meth:`_simulate` of (reference, trajectory indices) items, those on the same trajectories in one pass."""
        out: list = [None] * len(items)
        groups: dict = {}
        for n, (_, index) in enumerate(items):
            groups.setdefault(index, []).append(n)
        for index, members in groups.items():
            for n, preds in zip(members, self._simulate_all([items[n][0] for n in members], index)):
                out[n] = preds
        return out

    def _fit(self, cand: Candidate, ref, traj_index, start) -> dict | None:
        """Least squares over ``cand``'s parameters on the trajectories ``traj_index``."""
        lo, hi = np.log(cand.lower), np.log(cand.upper)

        def residuals(logv):
            return self._whitened(self._simulate_here(ref.with_effects(cand.settings(np.exp(logv))), traj_index),
                                  traj_index)

        try:
            res = scipy.optimize.least_squares(residuals, np.clip(np.log(start), lo + 1e-9, hi - 1e-9),
                                               bounds=(lo, hi), method="trf", diff_step=1e-3,
                                               max_nfev=self.settings.max_nfev, x_scale=1.0)
        except Exception as err:  # a candidate that cannot be simulated is just not the answer
            self.log(f"  {cand.label}: fit failed ({err})")
            return None
        values = np.exp(res.x)
        n, k = res.fun.size, len(values)
        sse = float(np.sum(res.fun ** 2))
        try:
            cov = np.linalg.pinv(res.jac.T @ res.jac) * sse / max(n - k, 1)
            unc = values * np.sqrt(np.clip(np.diag(cov), 0, None))
        except np.linalg.LinAlgError:
            unc = np.full(k, np.nan)
        return {"candidate": cand, "values": values, "uncertainty": unc, "sse": sse, "n": n,
                "bic": self._bic(sse, n, k)}

    def _round(self, ref, traj_index, skip_labels):
        base = self._whitened(self._simulate(ref, traj_index), traj_index)
        base_sse, n = float(np.sum(base ** 2)), base.size
        base_bic = self._bic(base_sse, n, 0)
        context = self._context(ref)
        # screening: every candidate's grid (and each drift / mismatch's one Gauss-Newton probe) in one pass
        cands = [cand for cand in catalogue(ref.params) if cand.label not in skip_labels]
        trials = [[np.array(cand.nominal, dtype=float) * (1 + _GAUSS_NEWTON_STEP)] if cand.nominal
                  else cand.grid(context) for cand in cands]
        refs = [ref] + [ref.with_effects(cand.settings(values)) for cand, grid in zip(cands, trials) for values in grid]
        preds = iter(self._simulate_all(refs, traj_index, coarse=True))
        coarse_base = self._whitened(next(preds), traj_index)
        screened = []
        for cand, grid in zip(cands, trials):
            if cand.nominal:
                screened.append(self._gauss_newton_step(cand, coarse_base, self._whitened(next(preds), traj_index)))
                continue
            best = None
            for values in grid:
                sse = float(np.sum(self._whitened(next(preds), traj_index) ** 2))
                if best is None or sse < best[0]:
                    best = (sse, values)
            screened.append((best[0], cand, best[1]))
        screened.sort(key=lambda item: item[0])
        # the most promising candidates' fits side by side, their simulations in shared passes
        top = screened[:self.settings.refine_top]
        lockstep = Lockstep(self._simulate_items)
        results = lockstep.run([lambda _, c=cand, v=values: self._fit(c, ref, traj_index, v)
                                for _, cand, values in top])
        fits = []
        for (_, cand, _), fit in zip(top, results):
            if fit is not None:
                fits.append(fit)
                self.log(f"  {cand.label}: {dict(zip(cand.keys, np.round(fit['values'], 5)))} "
                         f"SSE {fit['sse']:.4g} (before {base_sse:.4g})")
        fits = [f for f in fits if not f["candidate"].nominal or
                abs(f["values"][0] / f["candidate"].nominal[0] - 1) >= self.settings.min_relative_change]
        fits.sort(key=lambda f: f["bic"])
        return fits, base_sse, base_bic, n

    def _refit_jointly(self, effects, traj_index) -> dict:
        """Least squares over the parameters of all named effects at once; updates them in place."""
        cands = [e["best"]["candidate"] for e in effects]
        sizes = [len(c.keys) for c in cands]
        lo = np.log(np.concatenate([c.lower for c in cands]))
        hi = np.log(np.concatenate([c.upper for c in cands]))
        start = np.log(np.concatenate([e["best"]["values"] for e in effects]))

        def build(logv):
            ref, k = self.reference, 0
            for c, n in zip(cands, sizes):
                ref = ref.with_effects(c.settings(np.exp(logv[k:k + n])))
                k += n
            return ref

        def residuals(logv):
            return self._whitened(self._simulate_here(build(logv), traj_index), traj_index)

        # the Jacobian's columns (one per parameter) simulated in one pass
        columns = {"workers": LockstepMap(self._simulate_items)} if _LEAST_SQUARES_MAP else {}
        res = scipy.optimize.least_squares(residuals, np.clip(start, lo + 1e-9, hi - 1e-9), bounds=(lo, hi),
                                           method="trf", diff_step=1e-3, max_nfev=self.settings.max_nfev, **columns)
        values = np.exp(res.x)
        try:
            cov = np.linalg.pinv(res.jac.T @ res.jac) * float(np.sum(res.fun ** 2)) / max(res.fun.size - len(values), 1)
            unc = values * np.sqrt(np.clip(np.diag(cov), 0, None))
        except np.linalg.LinAlgError:
            unc = np.full(len(values), np.nan)
        k = 0
        for entry, n in zip(effects, sizes):
            entry["best"] = dict(entry["best"], values=values[k:k + n], uncertainty=unc[k:k + n])
            k += n
        sse = float(np.sum(res.fun ** 2))
        self.log(f"joint refit of {[c.label for c in cands]}: SSE {sse:.4g}")
        return dict(effects[-1]["best"], sse=sse, n=res.fun.size)

    @staticmethod
    def _gauss_newton_step(cand, base, r1):
        """One finite-difference Gauss-Newton step from the nameplate value: predicted SSE and value.

        ``base``: the whitened residual at the nameplate; ``r1``: at nameplate × (1 + step).
        """
        v0 = np.array(cand.nominal, dtype=float)
        g = (r1 - base) / np.log1p(_GAUSS_NEWTON_STEP)  # d residual / d log(value)
        gg = float(g @ g)
        if gg <= 0 or not np.isfinite(gg):
            return (float(base @ base), cand, v0)
        delta = float(-(g @ base) / gg)
        delta = float(np.clip(delta, np.log(cand.lower[0] / v0[0]), np.log(cand.upper[0] / v0[0])))
        predicted = float(np.sum((base + g * delta) ** 2))
        return (predicted, cand, v0 * np.exp(delta))

    def _context(self, ref) -> dict:
        """Largest reference-controller signals over the data: scales for the limit candidates."""
        ctx = {}
        try:
            sig = [ref.internal_signals(tr.x, tr.u) for tr in self.data]
        except Exception:  # references without internal signals (explicit models) give no hints
            return ctx
        if sig and "ilref_unlimited_d" in sig[0]:
            ctx["ilref_max"] = max(float(np.hypot(s["ilref_unlimited_d"], s["ilref_unlimited_q"]).max()) for s in sig)
            ctx["ilref_axis_max"] = max(float(np.maximum(np.abs(s["ilref_unlimited_d"]),
                                                         np.abs(s["ilref_unlimited_q"])).max()) for s in sig)
            ctx["vi_max"] = max(float(np.hypot(s["vi_cmd_d"], s["vi_cmd_q"]).max()) for s in sig)
            ctx["dw_max"] = max(float(np.abs(s["w"] - ref.params.wset).max()) for s in sig)
        names = self.data.state_names
        if "ig_d" in names and "ig_q" in names:
            i, j = names.index("ig_d"), names.index("ig_q")
            ctx["ig_max"] = max(float(np.hypot(tr.x[:, i], tr.x[:, j]).max()) for tr in self.data)
        return ctx

    # ------------------------------------------------------------------ the whole workflow
    def run(self, data: Dataset) -> dict:
        """Run where / name / add-and-show on ``data``; returns the report (see :func:`report_dict`)."""
        started = time.monotonic()
        s = self.settings
        self._prepare(data)
        data = self.data  # the inputs as replayed
        ref = self.reference
        self.start_sensitivities(ref)
        preds_before = self.corrected(self._simulate(ref))
        windows = self.detect(preds_before)
        self.log(f"noise level (median over states, relative to RMS): "
                 f"{np.median(self.noise / np.sqrt(np.mean(np.concatenate([t.x for t in data]) ** 2, 0))):.2e}; "
                 f"{len(windows)} disagreement window(s)")
        effects = []
        if windows:
            traj_index = sorted({w["traj_index"] for w in windows})
            skip = set()
            # the named catalogue augments the virtual-HIL plant; an explicit-model reference
            # goes straight to learning the residual
            for _ in range(s.max_effects if hasattr(ref, "with_effects") else 0):
                fits, base_sse, base_bic, n = self._round(ref, traj_index, skip)
                if not fits:
                    break
                best = fits[0]
                reduction = 1 - best["sse"] / base_sse
                if base_bic - best["bic"] < s.min_delta_bic or reduction < s.min_reduction:
                    self.log(f"no further candidate is supported (best {best['candidate'].label}: "
                             f"ΔBIC {base_bic - best['bic']:.1f}, reduction {reduction:.1%})")
                    break
                cand = best["candidate"]
                skip.add(cand.label)
                effects.append({"best": best, "reduction": reduction, "delta_bic": base_bic - best["bic"],
                                "ranking": [(f["candidate"].label, f["bic"]) for f in fits]})
                if len(effects) > 1:
                    # a first effect fitted alone absorbed part of the second: refit them together
                    best = self._refit_jointly(effects, traj_index)
                ref = self.reference
                for entry in effects:
                    ref = ref.with_effects(entry["best"]["candidate"].settings(entry["best"]["values"]))
                self.log(f"named {cand.label} {dict(zip(cand.keys, np.round(best['values'], 5)))} "
                         f"(SSE -{reduction:.1%})")
                if best["sse"] / best["n"] < s.chi2_done:
                    break  # the rest is noise
                remaining = self.detect(self.corrected(self._simulate(ref)))
                if not remaining:
                    break
            if not effects:
                from .residual import learn_unnamed_effect

                self.windows = windows
                unnamed = learn_unnamed_effect(self, ref, data)
                if unnamed is not None:
                    ref = unnamed["reference"]
                    effects.append({"unnamed": unnamed})
        preds_after = self.corrected(self._simulate(ref))
        self.augmented = ref
        self.preds_before, self.preds_after, self.windows = preds_before, preds_after, windows
        return report_dict(self, data, windows, effects, preds_before, preds_after, time.monotonic() - started)


def _runs(flags: np.ndarray, min_len: int, merge: int) -> list[tuple[int, int]]:
    """(start, end) index pairs of runs of True, merged across short gaps, at least min_len long."""
    idx = np.flatnonzero(flags)
    if idx.size == 0:
        return []
    runs = []
    start = prev = int(idx[0])
    for i in idx[1:]:
        i = int(i)
        if i - prev > merge:
            runs.append((start, prev))
            start = i
        prev = i
    runs.append((start, prev))
    return [(a, b) for a, b in runs if b - a + 1 >= min_len]


def report_dict(flow: GapWorkflow, data, windows, effects, before, after, seconds) -> dict:
    """The JSON report of the issue: effects, gap before/after (overall and per window), windows, noise."""
    rows = [(w["traj_index"], slice(w["i0"], w["i1"] + 1)) for w in windows]
    out_effects = []
    for entry in effects:
        if "unnamed" in entry:
            u = entry["unnamed"]
            out_effects.append({"name": "unnamed", "params": {"terms": u["terms"]},
                                "uncertainty": {}, "evidence": u["evidence"]})
            continue
        best = entry["best"]
        cand = best["candidate"]
        params = {k: float(v) for k, v in zip(cand.keys, best["values"])}
        if cand.name in ("param_drift", "gain_mismatch"):
            params = {"parameter": cand.keys[0], "value": params[cand.keys[0]]}
            unc = {"value": float(best["uncertainty"][0])}
        else:
            params.update({k: v for k, v in cand.fixed.items()})
            unc = {k: float(u) for k, u in zip(cand.keys, best["uncertainty"])}
        out_effects.append({
            "name": cand.name, "label": cand.label, "params": params, "uncertainty": unc,
            "evidence": {"sse_reduction_pct": 100 * entry["reduction"], "delta_bic": entry["delta_bic"],
                         "ranking": [{"candidate": label, "bic": bic} for label, bic in entry["ranking"]]},
        })
    window_rows = []
    for w, row in zip(windows, rows):
        window_rows.append({"t0": w["t0"], "t1": w["t1"], "traj": w["traj"], "states": w["states"],
                            "conditions": w["conditions"],
                            "gap_before": gap_percent(data, before, [row]),
                            "gap_after": gap_percent(data, after, [row])})
    noise_rel = flow.noise / np.maximum(np.sqrt(np.mean(np.concatenate([t.x for t in data]) ** 2, 0)), 1e-12)
    return {
        "effects": out_effects,
        "effect_missing": bool(out_effects),
        "gap_before": {"overall": gap_percent(data, before), "windows": [w["gap_before"] for w in window_rows]},
        "gap_after": {"overall": gap_percent(data, after), "windows": [w["gap_after"] for w in window_rows]},
        "windows": window_rows,
        "noise_level": {"per_state": dict(zip(data.state_names, flow.noise.tolist())),
                        "relative_median": float(np.median(noise_rel))},
        # per input: its noise, and the stretches held at their means (empty: exact inputs)
        "inputs_denoised": getattr(flow, "inputs_denoised", {}),
        "reference": flow.reference.describe() if hasattr(flow.reference, "describe") else {},
        "augmented": flow.augmented.describe() if hasattr(flow.augmented, "describe") else {},
        "seconds": seconds,
    }
