"""Estimators with one API: PISML (with and without the Jacobian loss) and the paper's baselines.

``make_estimator(method, config).fit(train, smallsignal, callback, should_stop)`` returns the
estimator; learned attributes end in ``_``:

- ``model_``: the final model (simulate, jacobian, eigenvalues, equilibrium, n_parameters);
- ``explicit_model_``: an :class:`~pisml_ros.model.ExplicitModel` where the method has one;
- ``metrics_``: timings, losses, parameter counts; ``history_``: training curves.

``callback(StageUpdate)`` reports progress and each stage's model as soon as it exists
(backbone → hybrid → explicit), from the thread that runs ``fit``.

Which of a PISML fit's candidate explicit models becomes ``explicit_model_`` is :mod:`.selection`'s
choice; this module runs the fit and its further tries, which ask the selection what it would take.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable

import numpy as np

from ..data import Dataset
from ..data.dataset import concat_datasets, records_at_rest, steady_start_mean
from ..model import ExplicitModel
from ..model.expressions import term_set
from .backbone import fit_backbone, reference_points
from .config import IdentConfig
from .library import (centred_terms, coupling_separation, extended_library, filter_row_mask, integrator_row_mask,
                      grid_voltage_pairs, power_row_mask,
                      monomial_basis, physics_library, rebased, term_degrees)
from .limiter import fit_reference_limit
from .noise import estimated_snr_db, input_noise_std, piecewise_constant_inputs
from .roles import SignalRoles
from .selection import (LONG_BRANCH_SUFFIX, SELECTION_WINDOW, _any_beats_hold, _configured_selection,
                        _noisy_choice_needs_retry, _prune_round_name, _refinement_family, _refinement_suffices,
                        _unpruned_refinement_lost, _with_equilibria, _would_choose, _would_choose_misfits)
from .trajfit import SHOOTING_PARTS_MAX, blas_threads, window_costs

METHODS = ("pisml", "pisml-nojac", "std-sindy", "mod-sindy", "node")
# the candidate name of the backbone fitted with the noise correction (the second refinement start)
NOISE_COMPENSATED = "noise-compensated backbone"
# the names of the candidates the low-SNR windows' pass refined end so (IdentConfig.refine_growing_windows_low_snr)
LOW_SNR_SUFFIX = " in low-SNR windows"


class IdentificationCancelled(Exception):
    """fit() stopped because should_stop() returned True."""


@dataclasses.dataclass
class StageUpdate:
    """Progress of a fit: ``stage`` (backbone | training | hybrid | distillation |
    explicit (before refinement) | refinement | selection | explicit),
    overall ``progress`` in [0, 1], ``epoch``, current ``losses`` and, when a stage's model is ready, ``model``."""

    stage: str
    progress: float
    epoch: int = 0
    losses: dict = dataclasses.field(default_factory=dict)
    model: object | None = None


class _Estimator:
    method = ""

    def __init__(self, config: IdentConfig | None = None):
        self.config = config or IdentConfig()

    def _start(self, train: Dataset, smallsignal: Dataset | None, callback, should_stop):
        """Checks and the fit's state; returns the records every stage works on: ``train`` and
        ``smallsignal`` with noisy measured inputs held constant where they are
        (``config.input_denoise``; what was done is in ``inputs_denoised_``, empty if nothing)."""
        if len(train) == 0:
            raise ValueError("no training trajectories")
        self.config.roles.check(train.state_names, train.input_names)
        self._callback = callback or (lambda update: None)
        self._should_stop = should_stop or (lambda: False)
        self._t0 = time.monotonic()
        self.metrics_ = {}
        self.history_ = {}
        self.inputs_denoised_ = {}
        if self.config.input_denoise == "off":
            return train, smallsignal
        held = {}
        for label, records in (("training", train), ("smallsignal", smallsignal)):
            sigma = input_noise_std(records) if records is not None and len(records) else None
            if sigma is None or not np.any(sigma > 0):
                held[label] = records
                continue
            held[label], self.inputs_denoised_[label] = piecewise_constant_inputs(
                records, sigma=sigma, interval_threshold=self.config.input_interval_threshold,
                edge_width=self.config.input_edge_width)
        if self.inputs_denoised_:
            self.metrics_["inputs_denoised"] = 1.0
        return held["training"], held["smallsignal"]

    def _emit(self, stage, progress, epoch=0, losses=None, model=None):
        if self._should_stop():
            raise IdentificationCancelled(f"{self.method}: cancelled during {stage}")
        self._progress = float(progress)  # the last reported: a later optional stage continues from it
        passes = getattr(self, "_refinement_pass", None)
        if passes is not None and 0.7 <= progress <= 0.99:
            # pass k of n of the refinement (low-SNR records) reports within its share of 0.7-0.99
            progress = 0.7 + (passes[0] * 0.29 + (progress - 0.7)) / passes[1]
        self._callback(StageUpdate(stage, float(progress), int(epoch), dict(losses or {}), model))

    def _finish(self, model, explicit):
        self.model_ = model
        self.explicit_model_ = explicit
        self.metrics_["seconds"] = time.monotonic() - self._t0
        self.metrics_["n_parameters"] = float(model.n_parameters)
        if explicit is not None:
            explicit.metadata.setdefault("identification", {}).update(
                {"method": self.method, "seconds": round(self.metrics_["seconds"], 3)})
            if self.inputs_denoised_:
                explicit.metadata["identification"]["inputs_denoised"] = self.inputs_denoised_
                caution = _input_noise_warning(self.inputs_denoised_)
                if caution and "selection" in explicit.metadata:
                    explicit.metadata["selection"].setdefault("warnings", []).append(caution)
        return self


def _meta(method: str, config: IdentConfig, train: Dataset, smallsignal: Dataset | None) -> dict:
    records = [*train, *(smallsignal if smallsignal is not None else [])]
    inputs = np.concatenate([tr.u for tr in records])
    # where the data were: an analysis outside this range extrapolates (analysis.data_coverage)
    input_range = {name: [float(inputs[:, j].min()), float(inputs[:, j].max())]
                   for j, name in enumerate(train.input_names)}
    # (None on clean records, JSON having no inf, and on records too short to tell noise from signal)
    snr = estimated_snr_db(train) if any(len(tr) > 2 for tr in train) else np.inf
    return {"method": method, "config": config.to_dict(), "reference_points": reference_points(train, also=smallsignal),
            "training": {"trajectories": len(train), "samples": train.n_samples,
                         # the records' SNR as the engine estimated it (IdentConfig.low_snr_below_db)
                         "estimated_snr_db": round(snr, 2) if np.isfinite(snr) else None,
                         "smallsignal_trajectories": len(smallsignal) if smallsignal is not None else 0,
                         "records_at_rest": records_at_rest(train),
                         "input_range": input_range,
                         # the bandwidth the records pin (analysis.operating_point.bandwidth_note)
                         "sample_period": float(train.dt)}}


def backbone_span(config: IdentConfig, dt: float) -> int:
    """Samples per window of the backbone's integral form at the sample period ``dt`` (s):
    ``config.backbone_span``, fewer where that would be longer than ``config.backbone_span_max_s``
    (0: no bound), but not fewer than 3 by the bound.

    Examples
    --------
    >>> backbone_span(IdentConfig(), 1e-4), backbone_span(IdentConfig(), 2e-4), backbone_span(IdentConfig(), 5e-5)
    (10, 5, 10)
    """
    if config.backbone_span_max_s <= 0:  # dt > 0: datasets reject times that do not increase
        return config.backbone_span
    # round, not floor: 1 ms at 10 kHz is 10 samples, not 9 by float division
    return min(config.backbone_span, max(3, round(config.backbone_span_max_s / dt)))


def _input_noise_warning(denoised: dict) -> str | None:
    """The caution for a model identified from noisy measured inputs (``denoised``: per record set,
    :func:`~.noise.piecewise_constant_inputs`' report), or None where their noise is below 100 dB."""
    levels = {}
    for report in denoised.values():
        for name, entry in report.items():
            if entry["sigma"] > 1e-5 * entry["rms"]:
                levels[name] = min(levels.get(name, np.inf), entry["snr_db"])
    if not levels:
        return None
    text = ", ".join(f"{name} at {snr:.0f} dB SNR" for name, snr in levels.items())
    return (f"the measured inputs carry noise ({text}): the identification held them at their means where they "
            f"are constant, but the model takes its inputs as exact and the noise left in them biases it "
            f"(40 dB on the inputs as well as the states, the protocol's recordings 0-9: 0.52-5.1 % IOD, "
            f"0.70-8.4 % OOD, none within the 40 dB targets; README, 'Noise on the measured inputs'); "
            f"measure or filter the grid voltage and angle with less noise where you can")


#: the caution on a fit of noisy records without small-signal records. Measured (stop 52, the protocol's
#: recordings 0-5 at 40 dB fitted without their small-signal records, IOD / OOD %): 0.202 / 0.446
#: (spurious unstable at ug 0.2-0.6), 0.876 / 1.18, 1.13 / 1.71 (spurious at 0.2-1.1, inside the data),
#: 0.384 / 0.554, 0.338 / 1.05 (spurious at 0.2), 0.459 / 0.259 (spurious at 0.2): 1 of 6 within both
#: 40 dB targets with no spurious mode, spurious modes on 4 of 6; with them 5 of 6 and none. Clean
#: records 0 and 1 gave the same figures either way (0.0099 / 0.015 %, 72 coefficients: the exact records
#: pin the slow modes), so clean fits get no caution. Stop 102 (two neural residuals; the scenarios' "no
#: small-signal records" seeds 0-1, `bench/candidates.py --scenario "no small-signal records"` seeds 2-9):
#: 5 of 10 within both targets with no spurious mode (seed 3 spurious at 1.0-1.1; seeds 2 and 3 kept an
#: unpruned refinement of 204 / 224 coefficients), against make bench's 10 of 10 with them.
NO_SMALLSIGNAL_WARNING = (
    "no small-signal records: the Jacobian-consistency loss was off and the slow modes rest on the noisy "
    "trajectories alone (on the benchmark's 40 dB recordings 0-9 this met the accuracy targets with no spurious "
    "unstable mode on 5 of 10 fits, against 10 of 10 with them); give small-signal records (small ug and theta_g "
    "steps from rest, --smallsignal) where you can")


class ModSINDy(_Estimator):
    """Mod-SINDy: the physics library Θ, finite-difference derivatives, ridge regression (1e-6)."""

    method = "mod-sindy"

    def fit(self, train: Dataset, smallsignal: Dataset | None = None, callback=None, should_stop=None):
        import pysindy as ps

        from .derivatives import finite_difference_derivatives

        train, smallsignal = self._start(train, smallsignal, callback, should_stop)
        # the paper's physics library: no rotating-frame couplings
        terms = physics_library(self.config.roles, train.state_names, coupling=False)
        ts = term_set(terms, tuple(train.state_names) + tuple(train.input_names))
        theta = np.concatenate([ts.evaluate(np.concatenate([tr.x, tr.u], 1)) for tr in train])
        xdot = np.concatenate(finite_difference_derivatives(train))
        opt = ps.STLSQ(threshold=0.0, alpha=1e-6).fit(theta, xdot)
        model = ExplicitModel(train.state_names, train.input_names, terms, np.atleast_2d(opt.coef_).T,
                              _meta(self.method, self.config, train, smallsignal))
        self._emit("explicit", 1.0, model=model)
        return self._finish(model, model)


class StdSINDy(_Estimator):
    """Std SINDy: polynomial library of degree 2 over MinMax-scaled signals, STLSQ threshold 0.005.

    The terms of the explicit model are written over the scaled signals (``(x - lo)/(hi - lo)``),
    so the JSON still rebuilds f(x, u) exactly.
    """

    method = "std-sindy"

    def fit(self, train: Dataset, smallsignal: Dataset | None = None, callback=None, should_stop=None):
        import itertools

        import pysindy as ps

        from .derivatives import finite_difference_derivatives

        train, smallsignal = self._start(train, smallsignal, callback, should_stop)
        names = list(train.state_names) + list(train.input_names)
        z = np.concatenate([np.concatenate([tr.x, tr.u], 1) for tr in train])
        lo, hi = z.min(axis=0), z.max(axis=0)
        span = np.where(hi - lo > 1e-12, hi - lo, 1.0)
        scaled = [f"(({n} - {float(lo[k])!r})/{float(span[k])!r})" for k, n in enumerate(names)]
        terms = ["1", *scaled, *[f"{a}*{b}" for a, b in itertools.combinations_with_replacement(scaled, 2)]]
        theta = term_set(terms, names).evaluate(z)
        n_x = len(train.state_names)
        # derivatives of the scaled states; coefficients go back to 1/s of the raw states below
        xdot = np.concatenate(finite_difference_derivatives(train)) / span[:n_x]
        opt = ps.STLSQ(threshold=0.005, alpha=0.05).fit(theta, xdot)
        coef = np.atleast_2d(opt.coef_).T * span[None, :n_x]
        model = ExplicitModel(train.state_names, train.input_names, terms, coef,
                              _meta(self.method, self.config, train, smallsignal))
        self._emit("explicit", 1.0, model=model)
        return self._finish(model, model)


class PureNODE(_Estimator):
    """Pure NODE: the MLP alone as the vector field, trained through the ODE solver (no physics, no
    Jacobian loss); no explicit model."""

    method = "node"

    def fit(self, train: Dataset, smallsignal: Dataset | None = None, callback=None, should_stop=None):
        from .neural import NeuralModel

        train, smallsignal = self._start(train, smallsignal, callback, should_stop)
        field = _train_field(self, train, None, backbone=None, lambda_pert=0.0)
        model = NeuralModel(field, train.state_names, train.input_names, reference_points(train), kind="neural ODE")
        self._emit("hybrid", 1.0, model=model)
        return self._finish(model, None)


class PISML(_Estimator):
    """PISML: sparse physics backbone + neural residual trained through the ODE solver (+ Jacobian
    consistency on small-signal data), distilled over Θ_ext, merged, and refined on trajectories.

    Parameters
    ----------
    config : IdentConfig
    use_jacobian : bool
        False gives the "PISML without the Jacobian loss" ablation (small-signal data unused).
    """

    def __init__(self, config: IdentConfig | None = None, use_jacobian: bool = True):
        super().__init__(config)
        self.use_jacobian = use_jacobian
        self.method = "pisml" if use_jacobian else "pisml-nojac"

    def fit(self, train: Dataset, smallsignal: Dataset | None = None, callback=None, should_stop=None):
        train, smallsignal = self._start(train, smallsignal, callback, should_stop)
        beside: list = []  # a refinement started early (_Beside), ended here whatever happens
        try:
            return self._fit(train, smallsignal, beside)
        finally:
            for job in beside:
                job.close()

    def _fit(self, train: Dataset, smallsignal: Dataset | None, beside: list):
        from .noise import noise_floor_error

        cfg = self.config
        smallsignal = smallsignal if self.use_jacobian else None
        signals = list(train.state_names) + list(train.input_names)
        # 1. backbone
        started = time.monotonic()
        separation = coupling_separation(np.concatenate([tr.x for tr in train]), train.state_names, cfg.roles)
        coupling = bool(cfg.roles.frequency) and separation >= cfg.coupling_min_separation
        self.metrics_["coupling_separation"] = separation
        self.metrics_["frequency_couplings"] = float(coupling)
        theta_terms = physics_library(cfg.roles, train.state_names, coupling=coupling)
        span = backbone_span(cfg, train.dt)
        backbone = fit_backbone(train, theta_terms, span=span, threshold=cfg.backbone_threshold,
                                alpha=cfg.backbone_alpha)
        backbone.metadata.update(_meta(self.method, cfg, train, smallsignal))
        backbone.metadata["stage"] = "backbone"
        backbone.metadata["backbone_span_samples"] = span
        backbone.metadata["frequency_couplings"] = {"used": coupling, "separation": round(separation, 4),
                                                    "min_separation": cfg.coupling_min_separation}
        self.backbone_ = backbone
        self.metrics_["backbone_seconds"] = time.monotonic() - started
        self._emit("backbone", 0.05, model=backbone)
        noisy = _noisy(train)
        compensated = None
        if cfg.backbone_noise_correction and noisy:
            compensated = fit_backbone(train, theta_terms, span=span, threshold=cfg.backbone_threshold,
                                       alpha=cfg.backbone_alpha, noise_correction=True)
            compensated.metadata = {**backbone.metadata, "backbone_fit": compensated.metadata["method"],
                                    "noise_std": compensated.metadata["noise_std"]}
        # candidates are scored on every record given: the small-signal records run freely for 0.1 s
        # test the equilibrium and the slow modes that 40 ms of training record hardly show.
        # Measured (40 dB, benchmark recording 2): on the training records alone the pruned
        # refinement from the merged model won, 1.72 % against 1.76 % (test: 0.47 / 2.13 % IOD /
        # OOD); the small-signal records' errors, 10.5 % against 3.9 %, pick the other (0.31 / 0.39 %)
        scoring = concat_datasets([train, smallsignal]) if smallsignal is not None and len(smallsignal) else train
        verdicts: dict = {}  # stability at the records' rest points, by candidate (selection, refinement start)

        def refine_model(start_model, start_error, progress, growing=None, config=None):
            config = config or cfg
            errors: dict = {}
            begin = _couplings_centred(_integrators_restricted(start_model, config, train), config, train)
            refined = refine_explicit(begin, train, smallsignal, config, progress, start_error=start_error,
                                      errors=errors, scoring=scoring, growing=growing)
            # scored here, on the refinement's own thread: where two run side by side, the first
            # to end scores its models while the other still runs
            errors.update(training_errors({name: model for name, model in refined.items() if name not in errors},
                                          scoring))
            return refined, errors

        # the limit search needs the records alone: it runs on the first thread a refinement leaves
        limit_search = _Deferred(lambda: fit_reference_limit(train, cfg.roles, span=cfg.limiter_span)) \
            if cfg.refine and cfg.limiter_search else None
        early = self._early_second_start(compensated, backbone, scoring, verdicts, refine_model, limit_search)
        if early is not None:
            beside.append(early[1])
        # 2. hybrid: Ξ and N(x, u) trained together through the ODE solver
        started = time.monotonic()
        field = _train_field(self, train, smallsignal, backbone=backbone,
                             lambda_pert=cfg.lambda_pert if self.use_jacobian else 0.0)
        trained_backbone, hybrid = _hybrid_model(field, train, theta_terms, backbone)
        self.hybrid_ = hybrid
        self.metrics_["hybrid_seconds"] = time.monotonic() - started
        self._emit("hybrid", 0.6, model=hybrid)
        # 3. distillation of N over Θ_ext, merged with the trained backbone
        started = time.monotonic()
        ext = extended_library(cfg.roles, train.state_names, degree=cfg.distill_degree)
        explicit = _distilled(hybrid, trained_backbone, train, ext, signals, cfg)
        self.distilled_ = explicit
        self.metrics_["distill_seconds"] = time.monotonic() - started
        self._emit("distillation", 0.7, losses={"terms": len(explicit.terms), "nonzero": explicit.n_parameters})
        # 4. every term of Θ and Θ_ext re-fitted jointly on the data (equation error), then
        # fine-tuning of the best of those and the merged model on trajectories (+ small-signal responses)
        candidates = {"backbone": backbone, "trained backbone": trained_backbone, "distilled": explicit}
        started = time.monotonic()
        library, _ = monomial_basis([*theta_terms, *ext], signals)
        candidates.update(_sparse_refits(explicit, library, train, cfg))
        self.metrics_["refit_seconds"] = time.monotonic() - started
        if compensated is not None:
            candidates[NOISE_COMPENSATED] = compensated
        # (the refinement started early has its start's score already)
        scores = training_errors(candidates, scoring, known={NOISE_COMPENSATED: early[0]} if early else None)
        hold = hold_error(scoring)
        # what the noise alone leaves: the yardstick of the rescue and of the selection's caution
        noise_floor = noise_floor_error(scoring)
        # the selection's tolerance counts from it on noisy records (IdentConfig.selection_floor_tolerance)
        tolerance_floor = noise_floor if noisy else None
        if early is not None:
            early[1].resume_caller()  # the refinement shares the threads out again
        if cfg.refine:
            # refinement takes most of the time: the best explicit model so far goes out first
            preliminary = _configured_selection(explicit, candidates, scores, cfg, verdicts, hold, tolerance=0.0)
            preliminary.metadata["stage"] = "explicit (before refinement)"
            self._emit("explicit (before refinement)", 0.7, model=preliminary)
            started = time.monotonic()
            context = _RefinementContext(explicit, train, scoring, signals, library, noisy, hold, noise_floor,
                                         tolerance_floor, refine_model)
            # on low-SNR records a second pass refines the same starts in the low-SNR growing windows
            # (IdentConfig.refine_growing_windows_low_snr); its families compete, renamed (LOW_SNR_SUFFIX)
            passes = refinement_passes(train, cfg)
            unrefined = dict(candidates)
            self.metrics_["refinement_passes"] = float(len(passes))
            # on noisy records (not low-SNR: there the second pass is the other family) more neural
            # residuals from other seeds, each refined from its own start (IdentConfig.residual_fits)
            more = cfg.residual_fits - 1 if noisy and len(passes) == 1 else 0
            shares = len(passes) + more
            try:
                for k, (pass_config, pass_suffix) in enumerate(passes):
                    self._refinement_pass = (k, shares) if shares > 1 else None
                    if not pass_suffix:
                        self._refine_pass(pass_config, context, candidates, scores, verdicts, early, limit_search)
                        continue
                    # the second pass sees the candidates from before the refinement only, as a fit would
                    own = (dict(unrefined), {name: scores[name] for name in unrefined})
                    metadata_before = explicit.metadata.copy()
                    self._refine_pass(pass_config, context, *own, {}, None, None)
                    _merge_pass((candidates, scores), own, set(unrefined), pass_suffix)
                    # the pass's own records of its starts and tries, beside the first pass's
                    written = explicit.metadata
                    explicit.metadata = metadata_before
                    explicit.metadata["low_snr_pass"] = {
                        "windows": list(pass_config.refine_growing_windows), "suffix": pass_suffix,
                        **{key: value for key, value in written.items()
                           if key not in metadata_before or value is not metadata_before[key]}}
                records = []
                for k in range(1, 1 + more):
                    self._refinement_pass = (len(passes) + k - 1, shares)
                    records.append(self._residual_family(k, context, candidates, scores, backbone, theta_terms,
                                                         ext, smallsignal))
                if records:
                    explicit.metadata["residual_fits"] = records
            finally:
                self._refinement_pass = None
            self.metrics_["refine_seconds"] = time.monotonic() - started
        # 5. the explicit model is the candidate that best reproduces the records when run freely
        # from their rest states or first samples (refinement that made things worse is dropped), or
        # the sparsest pruned refinement nearly as good
        unscored = {name: model for name, model in candidates.items() if name not in scores}
        scores.update(training_errors(unscored, scoring))
        self.candidates_ = candidates
        # on low-SNR records the run-free score can prefer a model that lost a fast mode: the short
        # windows judge them too (IdentConfig.selection_window_excess)
        short_costs = None
        if noisy and cfg.refine and 0 < cfg.selection_window_excess < np.inf and low_snr(train, cfg):
            started = time.monotonic()
            short_costs = window_costs({name: model for name, model in candidates.items()
                                        if scores.get(name, np.inf) < hold}, train, SELECTION_WINDOW)
            self.metrics_["window_cost_seconds"] = time.monotonic() - started
        # (on noisy records the refinement is what fits the trajectories: a model from before it is a caution)
        explicit = _configured_selection(explicit, candidates, scores, cfg, verdicts, hold, noise_floor=noise_floor,
                                         refinement_expected=cfg.refine and noisy, tolerance_floor=tolerance_floor,
                                         window_costs=short_costs)
        explicit.metadata["selection"]["scored_on"] = ("training and small-signal records" if scoring is not train
                                                       else "training records")
        if noisy and not (smallsignal is not None and len(smallsignal)):
            explicit.metadata["selection"]["warnings"].append(NO_SMALLSIGNAL_WARNING)
        self.metrics_["training_error_pct"] = scores[explicit.metadata["selection"]["chosen"]]
        self._emit("selection", 0.99, losses={f"train_err_{k.replace(' ', '_')}": v for k, v in scores.items()})
        explicit.metadata["stage"] = "explicit"
        self.metrics_["explicit_nonzero"] = float(explicit.n_parameters)
        self.metrics_["hybrid_parameters"] = float(hybrid.n_parameters)
        self._emit("explicit", 1.0, model=explicit)
        return self._finish(explicit, explicit)

    def _refine_pass(self, cfg: IdentConfig, context: "_RefinementContext", candidates: dict, scores: dict,
                     verdicts: dict, early, limit_search) -> None:
        """One refinement pass with ``cfg``: every start (side by side, or the second where the first's
        family does not suffice), the clean growing fallback, the limit's family, the noisy rescue and
        the unrestricted fallback, each adding its refined models to ``candidates`` and ``scores`` (in
        place) and its record to ``context.explicit.metadata``. ``early`` is the refinement started
        beside the hybrid's training (:meth:`_early_second_start`, or None); ``limit_search`` the
        limit search (a :class:`_Deferred`, or None: not in this pass)."""
        explicit, hold, noisy = context.explicit, context.hold, context.noisy
        noise_floor, tolerance_floor = context.noise_floor, context.tolerance_floor
        starts = _refinement_starts(candidates, scores, explicit.metadata.get("reference_points") or [],
                                    verdicts)
        explicit.metadata["refinement_starts"] = list(starts)

        def refine_from(start, progress, growing=None, config=None):
            return context.refine_model(candidates[start], scores[start], progress, growing, config or cfg)

        def add(k, refined, errors, suffix=None, start=None):
            if suffix is None:
                suffix = "" if k == 0 else f" from {starts[k]}"
            for name, model in refined.items():
                model.metadata["refinement"]["start"] = start or starts[k]
                candidates[name + suffix] = model
            # (refine_from scored them all)
            scores.update({name + suffix: error for name, error in errors.items()})

        # the windows of one start are shared out over the threads only where its terms'
        # gradients are thread-safe (TermSet.thread_safe_gradient): else the two starts side by
        # side are quicker
        shared = term_set(candidates[starts[0]].terms, context.signals).thread_safe_gradient()
        # on clean data the second half of the refinement's progress is kept for the fallback below
        share = 0.28 if noisy or not cfg.refine_growing_windows else 0.14
        running = []
        if early is not None:
            if starts[1:] == [NOISE_COMPENSATED]:
                running = [early[1]]
            else:  # (not met: the same verdicts and score chose it early)
                early[1].close()
        if _both_starts(cfg) or len(starts) == 1 or not shared:
            outcomes = _side_by_side(refine_from, starts[:len(starts) - len(running)],
                                     lambda fraction, losses: self._emit(
                                         "refinement", 0.7 + share * fraction, losses=losses),
                                     after=limit_search.run if limit_search is not None else None,
                                     running=running)
            for k, outcome in enumerate(outcomes):
                add(k, *outcome)
            threads = _threads_for(len(starts))
            if len(starts) > 1:
                # (on one thread, where the gradients are not thread-safe, the two ran one after the other)
                explicit.metadata["refinement_second_start"] = {"start": starts[1], "run": True,
                                                                "side_by_side": threads > 1,
                                                                "early": bool(running)}
            if running:
                self.metrics_["refinement_early_seconds"] = running[0].seconds
            self.metrics_["refinement_threads"] = float(threads)
        else:
            # the first start alone on every thread; the second only where the first's family
            # does not give a model consistent with the records' rest points (IdentConfig.refine_starts).
            # The limit search needs the records alone: it runs beside that refinement, the BLAS
            # pools held at one thread until both end (threadpoolctl's limit is process-wide: the
            # search's and the fits' own limits, set and restored on two threads, would interleave)
            with blas_threads(1 if limit_search is not None else None, user_api="blas"):
                if limit_search is not None:
                    limit_search.start()
                try:
                    add(0, *refine_from(starts[0], lambda fraction, losses: self._emit(
                        "refinement", 0.7 + 0.28 * 0.5 * fraction, losses=losses)))
                finally:
                    if limit_search is not None:
                        limit_search.wait()
            first_lost = _unpruned_refinement_lost(scores, hold)
            needed = first_lost or not _refinement_suffices(explicit, candidates, scores, cfg, verdicts,
                                                            hold, tolerance_floor)
            explicit.metadata["refinement_second_start"] = {"start": starts[1], "run": needed,
                                                            "first_lost": first_lost}
            if needed:
                add(1, *refine_from(starts[1], lambda fraction, losses: self._emit(
                    "refinement", 0.84 + 0.14 * fraction, losses=losses)))
            self.metrics_["refinement_starts_run"] = float(sum(
                name.startswith("refined") and LONG_BRANCH_SUFFIX not in name for name in candidates))
        if not noisy and cfg.refine_growing_windows and "distilled" in candidates:
            self._clean_growing_fallback(cfg, explicit, candidates, scores, verdicts, hold, starts, refine_from,
                                         add)
        # the limit's family before the further tries without its terms: where it ran and one of its
        # refined models reproduces the records better than holding their first states, the rescue
        # and the unrestricted fallback would refine models that cannot saturate (_limit_supersedes)
        if cfg.limiter_search:
            try:
                self._limiter_family(cfg, explicit, candidates, scores, verdicts, hold, noise_floor,
                                     context.library, context.train, context.scoring, refine_from, add, limit_search,
                                     tolerance_floor)
            except (ValueError, np.linalg.LinAlgError) as err:
                # a search that breaks down numerically costs its candidates, not the fit
                explicit.metadata.setdefault("limiter", {})["error"] = f"{type(err).__name__}: {err}"
        superseded = _limit_supersedes(explicit.metadata.get("limiter"), scores, hold)
        if noisy and cfg.refine_growing_windows and np.isfinite(cfg.refine_rescue_ratio):
            self._noisy_rescue(cfg, explicit, candidates, scores, verdicts, hold, starts, noise_floor,
                               refine_from, add, superseded)
        if cfg.filter_terms == "physics":
            self._unrestricted_fallback(cfg, explicit, candidates, scores, verdicts, hold, starts,
                                        noise_floor if noisy else None, refine_from, add, superseded)

    def _residual_family(self, k: int, context: "_RefinementContext", candidates: dict, scores: dict,
                         backbone: ExplicitModel, theta_terms: list, ext: list, smallsignal) -> dict:
        """The neural residual trained again from seed ``config.seed + k``, distilled, re-fitted and
        refined from its own best start as the first one was (a refinement pass of its own, without
        the limit search); its refined families join ``candidates`` and ``scores`` (in place),
        renamed `` (residual k+1)``, and compete in the selection (``IdentConfig.residual_fits``).
        Returns the pass's record: the seed, the suffix, the seconds, what the pass wrote of its
        starts and tries, and the metrics it set (the fit's own metrics stay the first pass's)."""
        started = time.monotonic()
        cfg = dataclasses.replace(self.config, seed=self.config.seed + k, limiter_search=False)
        train, signals, suffix = context.train, context.signals, f" (residual {k + 1})"
        stage = f"training{suffix}"
        field = _train_field(self, train, smallsignal, backbone, cfg.lambda_pert if self.use_jacobian else 0.0,
                             config=cfg, history=stage,
                             report=lambda epoch, losses: self._emit(stage, 0.7, epoch=epoch, losses=losses))
        trained, hybrid = _hybrid_model(field, train, theta_terms, backbone)
        distilled = _distilled(hybrid, trained, train, ext, signals, cfg)
        own = {"distilled": distilled, **_sparse_refits(distilled, context.library, train, cfg)}
        own_scores = training_errors(own, context.scoring)
        unrefined, metrics_before = set(own), dict(self.metrics_)
        self._refine_pass(cfg, dataclasses.replace(context, explicit=distilled), own, own_scores, {}, None, None)
        _merge_pass((candidates, scores), (own, own_scores), unrefined, suffix)
        changed = {key: value for key, value in self.metrics_.items() if metrics_before.get(key) != value}
        self.metrics_ = metrics_before
        seconds = time.monotonic() - started
        self.metrics_["residual_fit_seconds"] = self.metrics_.get("residual_fit_seconds", 0.0) + seconds
        return {"seed": cfg.seed, "suffix": suffix, "seconds": round(seconds, 3),
                "distilled_error_pct": own_scores["distilled"], "metrics": changed,
                **{key: value for key, value in distilled.metadata.items() if key.startswith("refinement")}}

    def _early_second_start(self, compensated, backbone, scoring, verdicts, refine_model, limit_search=None):
        """``(score, job)``: the refinement from the noise-compensated backbone started now, beside the
        hybrid's training, where it will be the second refinement start (``IdentConfig.refine_starts``
        runs both side by side, torch has two threads, and it has an equilibrium at every rest point
        of the records, :func:`_refinement_starts`) and ``IdentConfig.refine_second_start_early`` is
        set; else None. That start needs the records and the backbone alone, and the hybrid's
        training, the distillation and the re-fits leave a core partly idle. ``limit_search`` (a
        :class:`_Deferred`, or None) runs on the job's thread after the refinement: that thread
        comes free before the first start's."""
        cfg = self.config
        if compensated is None or not (cfg.refine and cfg.refine_second_start_early and _both_starts(cfg)
                                       and _threads_for(2) >= 2):
            return None
        points = backbone.metadata.get("reference_points") or []
        score = training_errors({NOISE_COMPENSATED: compensated}, scoring)[NOISE_COMPENSATED]
        if not _with_equilibria([NOISE_COMPENSATED], {NOISE_COMPENSATED: compensated}, {NOISE_COMPENSATED: score},
                                points, verdicts):
            return None

        def job(progress):
            outcome = refine_model(compensated, score, progress)
            if limit_search is not None:
                limit_search.run()
            return outcome

        return score, _Beside(job, "pisml-refine-early")

    def _clean_growing_fallback(self, cfg, explicit, candidates, scores, verdicts, hold, starts, refine_from, add):
        """On clean data, where the model the selection would take does not reproduce the records
        within ``clean_growing_error``: the equation-error fits behind the sparse starts went wrong
        (coarse samples: quadrature and RK4 errors), so the merged model is refined in growing
        windows and pruned as noisy data are, and that family (``… from distilled``) joins the
        candidates. Recorded in the metadata (``refinement_growing_fallback``) and the metrics."""
        chosen = _would_choose(explicit, candidates, scores, cfg, verdicts, hold)
        if not scores[chosen] > cfg.clean_growing_error:
            return
        self._emit("refinement", 0.84)
        before = set(candidates)
        starts.append("distilled")
        add(len(starts) - 1, *refine_from("distilled", lambda fraction, losses: self._emit(
            "refinement", 0.84 + 0.14 * fraction, losses=losses), growing=True))
        explicit.metadata["refinement_growing_fallback"] = {
            "selected_before": chosen, "error_pct": scores[chosen], "added": sorted(set(candidates) - before)}
        self.metrics_["clean_growing_fallback"] = 1.0

    def _noisy_rescue(self, cfg, explicit, candidates, scores, verdicts, hold, starts, floor, refine_from, add,
                      superseded=False):
        """On noisy data, where the model the selection would take scores above
        ``refine_rescue_ratio`` times what the noise alone leaves (``floor``,
        :func:`~pisml_ros.ident.noise.noise_floor_error` of the scoring records): the growing-window
        stages, which have no stability prior, let the refinement wander to models that run away from
        the records' rest points (stop 41: the three of stop 40's 40 dB fits of the default plant
        above the ratio were its three worst), so the first start is refined again with
        ``refine_rescue_stability_weight`` in those stages, and that family (``… with growing
        prior``) joins the candidates. The same where that model is inconsistent with the records'
        rest points (:func:`_inconsistent_points`, at one or more), whatever its score: the
        selection takes such a model only where every candidate is, and one that runs away from
        where the records sat still fits 40 ms of them no worse for it (stop 65, the scenarios'
        5 kHz recording 0 at 40 dB: every candidate inconsistent at all 9 points, the chosen one
        unstable there at +6.6 to +8.5 1/s and at 2.2x the floor, 4.83 / 6.29 % IOD / OOD; with the
        rescue, its family's round 3, 0.442 / 0.236 % with 62 coefficients, no spurious mode, in
        69 s against 43 s). The same where that model is one from before the refinement (the
        backbone, the merged model, a re-fit: :func:`_refinement_family` None), whatever its score:
        on noisy records every refined candidate then ran away from the rest points or reproduced
        the records worse (stop 72, the plants' vendor-c recording 2 at 40 dB: the trained backbone,
        consistent at 1.39x the floor, 2.80 / 2.91 % IOD / OOD with 203 coefficients and W 3366 at
        ug 0.8; with the rescue its family's long-window round 2, 0.630 / 2.79 % with 88, W 1216, in
        90 s against 48 s). Where the model chosen then still scores above ``refine_retry_ratio`` and
        the second refinement start was skipped (``IdentConfig.refine_starts`` "fallback": the first
        family was consistent with the rest points), the second start is refined too: stop 46,
        protocol seed 19 at 40 dB, the first start's refinement scored 29 % and its rescue no better
        than 2.6x the floor (chosen: 2.06 / 2.36 % IOD / OOD, 146 coefficients), where the second
        start's family gives 0.48 / 0.81 % with 79, scoring 1.16x. Not where ``superseded``
        (:func:`_limit_supersedes`: the limit's family ran first and gave a model): the record says so
        (``superseded_by_limit``) and neither runs. Recorded in the metadata
        (``refinement_rescue``, ``refinement_second_start``) and the metrics."""

        def chosen_ratio():
            chosen, misfits = _would_choose_misfits(explicit, candidates, scores, cfg, verdicts, hold,
                                                    tolerance_floor=floor)
            return chosen, scores[chosen] / max(floor, 1e-12), misfits

        chosen, ratio, misfits = chosen_ratio()
        # (with the same weight as the first refinement's it would only repeat it)
        record = {"selected_before": chosen, "error_pct": scores[chosen], "noise_floor_pct": floor, "ratio": ratio,
                  "inconsistent_rest_points": misfits, "before_refinement": _refinement_family(chosen) is None,
                  "run": bool(_noisy_choice_needs_retry(chosen, ratio, misfits, cfg.refine_rescue_ratio)
                              and cfg.refine_rescue_stability_weight != cfg.refine_growing_stability_weight
                              and not superseded)}
        if superseded:
            record["superseded_by_limit"] = True
        explicit.metadata["refinement_rescue"] = record
        if record["run"]:
            before = set(candidates)
            rescue = dataclasses.replace(cfg, refine_growing_stability_weight=cfg.refine_rescue_stability_weight)
            add(0, *refine_from(starts[0], self._progress_on(), config=rescue), suffix=" with growing prior")
            record["added"] = sorted(set(candidates) - before)
            self.metrics_["refinement_rescue"] = 1.0
            ratio = chosen_ratio()[1]
            record["ratio_after"] = ratio
        second = explicit.metadata.get("refinement_second_start")
        if ratio > cfg.refine_retry_ratio and second is not None and not second["run"] and len(starts) > 1 \
                and not superseded:
            add(1, *refine_from(starts[1], self._progress_on()))
            second.update(run=True, after_rescue=True)
            self.metrics_["refinement_starts_run"] = 2.0

    def _limiter_family(self, cfg, explicit, candidates, scores, verdicts, hold, floor, library, train, scoring,
                        refine_from, add, limit_search: _Deferred, tolerance_floor: float | None = None):
        """The records may hold a saturation no library term has: a limit of a dq reference (its
        magnitude, or each axis) is fitted to them (``limit_search``, a :class:`_Deferred`
        :func:`~.limiter.fit_reference_limit` that ran beside the refinement where a thread came free;
        every fit since stop 56, 2–9 s on 2 cores, so that a limit acting in the records is reported,
        :func:`~.limiter.limit_note`, even where the model does without it). Where one is found
        and the model the selection would take reproduces the records far worse than their noise
        explains (the selection's caution: ``selection_warn_noise_ratio`` × ``floor`` +
        ``selection_warn_noise_margin``), its two terms S_d, S_q join (i) the sparse re-fit over every term
        (``re-fit +B % with limit``) and (ii) the model the selection would take, fitted in integral
        form on its own terms and those two (``chosen with limit``), or with the two alone fitted to
        what it leaves (``chosen plus limit``). The best two of them (those with an equilibrium at the
        records' rest points first) are refined side by side (``… with limit``, ``… with limit from
        <start>``), and all join the candidates. Recorded in the metadata (``limiter``) and the metrics.

        Measured (stop 54, `make bench`, the saturation plant, current limit 2.2 p.u.): clean from
        10.2 / 62.5 % IOD / OOD to 0.0224 / 0.093 % (the re-fit with the limit won), 40 dB from
        5.23 / 62.9 % to 1.48 / 5.46 % (the refinement from ``chosen plus limit``); with the plant's
        own reference and limit instead of the fitted ones the refinement reaches 0.36 / 1.07 %
        (scratch). From stop 56 the 40 dB row was back at 5.23 / 62.9 %: the family's models sat
        their equilibria 1.7–3.2 p.u. from the records' rest states, inconsistent with all 9, and
        lost; with the polish's rest prior (``limiter_rest_weight``, stop 65) 1.57 / 3.24 %.
        Stop 55, `make bench-limits`, a per-axis clamp (±1.6 / ±2.4 p.u.): clean 0.0227 / 0.142 %
        (recording 0; 0.84 / 40.0 % with the magnitude limit only), 40 dB found but not chosen
        (1.26 / 49.3 %). On the default plant no fit is above the caution's threshold, and the
        search finds no limit in any of the 41 record sets of stop 56's check (protocol recordings
        0–9 at 40 dB, clean, 20 and 30 dB; the other inverters; the scenarios at 40 dB).
        """
        chosen = _would_choose(explicit, candidates, scores, cfg, verdicts, hold, tolerance_floor=tolerance_floor)
        threshold = cfg.selection_warn_noise_ratio * floor + cfg.selection_warn_noise_margin
        record = {"selected_before": chosen, "error_pct": scores[chosen], "threshold_pct": threshold,
                  "run": True, "family": bool(scores[chosen] > threshold)}
        explicit.metadata["limiter"] = record
        limit = limit_search.value()  # (run beside the refinement where a thread came free)
        started = time.monotonic()
        record["found"] = limit is not None
        record["fit_seconds"] = limit_search.seconds
        self.metrics_["limiter_search"] = 1.0
        self.metrics_["limiter_seconds"] = record["fit_seconds"]
        if limit is None:
            return
        record["limit"] = limit.to_dict()
        if not record["family"]:
            # found, and said (limiter.limit_note), but the model reproduces the records as well as
            # their noise allows without it: its terms would not win the selection (stop 56, the clamp
            # plant at 40 dB, recording 1: refined anyway, +73 s, the same model chosen)
            return
        terms = limit.terms()
        new = {f"{name} with limit": model for name, model in
               _sparse_refits(explicit, [*library, *terms], train, cfg).items()}
        new["chosen with limit"] = _with_terms(candidates[chosen], terms, train, cfg.refit_span)
        new["chosen plus limit"] = _with_terms(candidates[chosen], terms, train, cfg.refit_span, refit=False)
        candidates.update(new)
        scores.update(training_errors(new, scoring))
        points = explicit.metadata.get("reference_points") or []
        sound = [name for name in new if np.isfinite(scores[name])] or list(new)
        eligible = _with_equilibria(sound, candidates, scores, points, verdicts)
        ranked = sorted(eligible, key=lambda name: scores[name]) + \
            sorted(set(sound) - set(eligible), key=lambda name: scores[name])
        starts = ranked[:2]
        record["refinement_starts"] = starts
        before = set(candidates)
        # the growing stages with the rescue's stability prior: the terms of the limit change the
        # equations where the limit is inactive as well, and without it the refinement ran away from
        # the records' rest points (measured below)
        # and the polish's rest prior (IdentConfig.limiter_rest_weight): the family's refined model
        # sat its equilibria ~3 p.u. from the records' rest states (measured there)
        prior = dataclasses.replace(cfg, refine_growing_stability_weight=cfg.refine_rescue_stability_weight,
                                    refine_rest_weight=cfg.limiter_rest_weight)
        progress = self._progress_on()
        outcomes = _side_by_side(lambda start, report: refine_from(start, report, config=prior), starts,
                                 lambda fraction, losses: progress(fraction, losses))
        for k, (start, outcome) in enumerate(zip(starts, outcomes)):
            add(0, *outcome, suffix=" with limit" + ("" if k == 0 else f" from {start}"), start=start)
        record["added"] = sorted(set(candidates) - before)
        chosen = _would_choose(explicit, candidates, scores, cfg, verdicts, hold, noise_floor=floor,
                               tolerance_floor=tolerance_floor)
        record["selected_after"] = chosen
        record["seconds"] = limit_search.seconds + (time.monotonic() - started)  # the search and the family
        self.metrics_["limiter_seconds"] = record["seconds"]

    def _progress_on(self):
        """A progress callback that goes on from where the refinement left it (0.84 after the first
        start alone, 0.98 after two, or after the starts run side by side) to 0.99."""
        base = max(getattr(self, "_progress", 0.84), 0.84)
        return lambda fraction, losses: self._emit("refinement", base + (0.99 - base) * fraction, losses=losses)

    def _unrestricted_fallback(self, cfg, explicit, candidates, scores, verdicts, hold, starts, floor, refine_from, add,
                               superseded=False):
        """With ``filter_terms`` "physics": where no restricted refinement gives a model that runs
        freely through the records better than holding their first states (every one broke down,
        blew up or drifted off), or where on noisy data the
        model the selection would take still scores above ``refine_retry_ratio`` times what the
        noise alone leaves (``floor``; None on clean data), each refinement start (at most two) is
        refined again with the output filter's rows free (``filter_terms`` "any"), and those
        families (``… unrestricted``) join the candidates. Stop 47, vendor-c seed 0 at 40 dB: both
        restricted starts were lost and the backbone was chosen (2.77 / 3.29 % IOD / OOD, 303
        coefficients, spurious modes at every ug), where the free rows' refinement gives 0.356 /
        0.272 % (stop 48, 107-113 s). On noisy data also where that model is inconsistent with the
        records' rest points (:func:`_inconsistent_points`), as the rescue (:meth:`_noisy_rescue`),
        which runs before this and may already give a consistent one, and where that model is one
        from before the refinement (``before_refinement``). Not where ``superseded``
        (:func:`_limit_supersedes`; the record says ``superseded_by_limit``). Recorded in the metadata
        (``refinement_unrestricted``) and the metrics."""
        chosen, misfits = _would_choose_misfits(explicit, candidates, scores, cfg, verdicts, hold,
                                                tolerance_floor=floor)
        # (a re-fit may be chosen on its merits: lost means no refinement ran through to a free run
        # that reproduces the records better than holding their first states. Stop 63, vendor-c seed 3
        # at 40 dB with both starts side by side: every refinement broke down but one prune round,
        # which ran through at 1247 % (the hold: 33 %); the backbone was chosen, 2.55 / 10.2 % IOD / OOD)
        lost = not _any_beats_hold(scores, [name for name in candidates if _refinement_family(name) is not None], hold)
        ratio = scores[chosen] / max(floor, 1e-12) if floor is not None else None
        # on noisy data, the rescue's question
        record = {"selected_before": chosen, "error_pct": scores[chosen], "refinement_lost": lost,
                  "ratio": ratio, "inconsistent_rest_points": misfits,
                  "before_refinement": _refinement_family(chosen) is None,
                  "run": bool((lost or (ratio is not None and
                                        _noisy_choice_needs_retry(chosen, ratio, misfits, cfg.refine_retry_ratio)))
                              and not superseded)}
        if superseded:
            record["superseded_by_limit"] = True
        explicit.metadata["refinement_unrestricted"] = record
        if not record["run"]:
            return
        before = set(candidates)
        free = dataclasses.replace(cfg, filter_terms="any")
        # both starts, as the first restricted start's family was not enough (vendor-c seed 0: the
        # free rows' first start gave no model consistent with the rest points, its second 0.356 %)
        progress = self._progress_on()
        for k, start in enumerate(starts[:2]):
            add(k, *refine_from(start, lambda fraction, losses, k=k: progress((k + fraction) / 2, losses),
                                config=free), suffix=("" if k == 0 else f" from {start}") + " unrestricted")
        record["added"] = sorted(set(candidates) - before)
        self.metrics_["refinement_unrestricted"] = 1.0


@dataclasses.dataclass
class _RefinementContext:
    """What every refinement pass of one fit (:meth:`PISML._refine_pass`) shares: the explicit model whose
    metadata records the passes, the records (training, and those the candidates are scored on), the
    signal names, the re-fit library (the limit's family extends it), whether the records are noisy,
    the hold error and the noise floor (%) the rescue and the selection measure from, and
    ``refine_model(start_model, start_error, progress, growing, config)``, which refines and scores."""

    explicit: ExplicitModel
    train: Dataset
    scoring: Dataset
    signals: list
    library: list
    noisy: bool
    hold: float
    noise_floor: float
    tolerance_floor: float | None
    refine_model: Callable


def _limit_supersedes(limiter: dict | None, scores: dict, hold: float) -> bool:
    """Whether the limit's family (``PISML._limiter_family``, its ``limiter`` record) ran and one of
    its refined models runs freely through the records better than holding their first states: then
    the rescue and the unrestricted fallback, which refine models without the limit's terms, are not
    run. A saturation that acts in the records is an effect those models lack, not a refinement that
    went astray (measured: the saturation plant at 40 dB, `make bench`, stop 87: none of their 24
    candidates chosen in either fit, ~130 s of the 40 dB fit's refinement stages)."""
    added = (limiter or {}).get("added") or []
    return _any_beats_hold(scores, [name for name in added if _refinement_family(name) is not None], hold)


def _both_starts(cfg: IdentConfig) -> bool:
    """Whether both refinement starts run side by side (``IdentConfig.refine_starts``: "both", or
    "auto" where torch has a second thread for the second start)."""
    return cfg.refine_starts == "both" or (cfg.refine_starts == "auto" and _threads_for(2) >= 2)


def _threads_for(jobs: int) -> int:
    """How many of ``jobs`` :func:`_side_by_side` runs at once: one per torch intra-op thread."""
    import torch

    return max(1, min(jobs, torch.get_num_threads()))


def _side_by_side(job: Callable, items: list, report: Callable[[float, dict], None],
                  workers: int | None = None, after: Callable[[], None] | None = None,
                  running: list | tuple = ()) -> list:
    """``[job(item, progress) for item in items]``, the jobs in threads side by side where torch has
    threads to share out (:func:`_threads_for`), else one after the other.

    ``progress(fraction, losses)`` is each job's own; ``report(fraction, losses)`` gets the jobs'
    mean fraction, from the calling thread only (the callers' callbacks are not thread-safe);
    ``workers`` overrides how many run at once. ``after()``, if given, runs on the first thread a
    job leaves free (after the jobs where they run one after the other), and has run when this
    returns: work of the caller's that needs no job's result (:class:`_Deferred`), done while the
    last job still runs, not after it on one core. ``running``: jobs already started on threads of
    their own (:class:`_Beside`), each counted as one of the jobs side by side (the threads are
    shared out over ``items`` and them) and in the mean fraction; their values follow the items'.
    An exception from ``report`` (cancellation) or from a job stops the other jobs (``running``
    too) at their next progress call and is raised here. Threads, not
    processes: most of the work is in torch calls that release the GIL (scipy's BLAS ``dsyrk`` in
    the normal equations holds it), and the jobs share the data. Measured on the 40 dB benchmark
    recording (2 vCPUs, before the syrk): the two refinements took 134 s one after the other (torch
    on 2 threads), 85 s side by side (one thread each).
    """
    import threading
    from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait

    import torch

    running = list(running)
    if workers is None:
        workers = _threads_for(len(items) + len(running)) - len(running) if running else _threads_for(len(items))
    workers = max(1, min(workers, len(items)))
    if workers == 1 and not running:
        results = [job(item, lambda fraction, losses, k=k: report((k + fraction) / len(items), losses))
                   for k, item in enumerate(items)]
        if after is not None:
            after()
        return results
    fractions = [0.0] * len(items)
    latest: dict = {}
    lock = threading.Lock()
    stop = threading.Event()

    def progress(k, fraction, losses):
        if stop.is_set():
            raise _StoppedBeside()
        with lock:
            fractions[k] = fraction
            latest.update(losses)

    def run(k, item):
        return job(item, lambda fraction, losses: progress(k, fraction, losses))

    threads = torch.get_num_threads()
    share = max(1, threads // (workers + len(running)))
    # torch sizes a thread's intra-op pool from its global setting when the thread first uses it:
    # the pool's threads start with their share; the caller's setting is restored after
    torch.set_num_threads(share)
    try:
        with blas_threads(share), ThreadPoolExecutor(workers, "pisml-refine") as pool:
            futures = [pool.submit(run, k, item) for k, item in enumerate(items)]
            if after is not None:
                # queued behind the jobs: it starts on the first thread one of them leaves
                futures.append(pool.submit(after))
            try:
                reported = -1.0
                while True:
                    done, pending = wait(futures, timeout=0.5, return_when=FIRST_EXCEPTION)
                    waiting = [beside for beside in running if not beside.done()]
                    if not pending and waiting:
                        # (wait() returns at once on finished futures: a loop on it alone would hold the GIL)
                        waiting[0].wait(0.5)
                    failed = [f.exception() for f in done if f.exception() is not None]
                    failed += [beside.error for beside in running if beside.error is not None]
                    if failed:
                        raise failed[0]
                    with lock:
                        fraction = (sum(fractions) + sum(beside.fraction for beside in running)) / \
                            (len(items) + len(running))
                        losses = dict(latest)
                    for beside in running:
                        losses.update(beside.losses())
                    if fraction > reported:
                        report(fraction, losses)  # may raise: cancelled
                        reported = fraction
                    if not pending and all(beside.done() for beside in running):
                        return [f.result() for f in futures[:len(items)]] + [beside.value() for beside in running]
            finally:
                stop.set()  # the jobs still running end at their next progress call
    finally:
        torch.set_num_threads(threads)
        for beside in running:
            # stopped where it still runs, and its BLAS limit lifted after this function's own, which restores to it
            beside.close()


class _Beside:
    """``job(progress)`` started now on a thread of its own with one torch and one BLAS thread,
    while the caller goes on with the rest (:func:`_side_by_side` takes it as one of its jobs).

    ``progress(fraction, losses)`` keeps the job's latest report (``fraction``, :meth:`losses`) for
    the caller to pass on: the callers' callbacks are not thread-safe. :meth:`stop` ends the job at
    its next progress call; :meth:`value` waits for it and returns its value, or raises what it
    raised. The BLAS pools stay at one thread until :meth:`close` (threadpoolctl's limit is
    process-wide), and the caller's torch at one until :meth:`resume_caller` (torch's is per thread).
    """

    def __init__(self, job: Callable, name: str = "pisml-beside"):
        import threading

        import torch

        self.fraction = 0.0
        self.error: BaseException | None = None
        self.seconds = 0.0
        self._job = job
        self._latest: dict = {}
        self._value = None
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._finished = threading.Event()
        self._caller_threads = torch.get_num_threads()
        self._blas = blas_threads(1, user_api="blas")
        self._blas.__enter__()
        ready = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(ready,), name=name, daemon=True)
        self._thread.start()
        ready.wait()
        # the caller goes on with one thread too, until resume_caller(): with two, its OpenMP team
        # spin-waits at every barrier while this job holds a core (measured, 40 dB recording 1 on
        # 2 cores: the hybrid's training took 22.6 s instead of 7.2 s)
        torch.set_num_threads(1)
        self._caller_resumed = False

    def _run(self, ready) -> None:
        import torch

        torch.set_num_threads(1)
        ready.set()
        started = time.monotonic()
        try:
            self._value = self._job(self._progress)
        except BaseException as err:  # raised again by value()
            self.error = err
        self.seconds = time.monotonic() - started
        self._finished.set()

    def _progress(self, fraction: float, losses: dict) -> None:
        if self._stopping.is_set():
            raise _StoppedBeside()
        with self._lock:
            self.fraction = fraction
            self._latest.update(losses)

    def losses(self) -> dict:
        with self._lock:
            return dict(self._latest)

    def done(self) -> bool:
        return self._finished.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait up to ``timeout`` seconds for the job to end; whether it has."""
        return self._finished.wait(timeout)

    def resume_caller(self) -> None:
        """The caller's torch threads as they were before this job started (call from the caller)."""
        import torch

        if not self._caller_resumed:
            torch.set_num_threads(self._caller_threads)
            self._caller_resumed = True

    def stop(self) -> None:
        """End the job at its next progress call and wait for it (its value is dropped)."""
        self._stopping.set()
        self._thread.join()

    def close(self) -> None:
        """:meth:`stop` where it still runs, the caller's threads resumed and the BLAS pools' limit
        lifted; idempotent (call from the caller)."""
        if not self.done():
            self.stop()
        self.resume_caller()
        if self._blas is not None:
            self._blas.__exit__(None, None, None)
            self._blas = None

    def value(self):
        self._thread.join()
        if self.error is not None:
            raise self.error
        return self._value


class _Deferred:
    """A computation run once: where a thread comes free (:func:`_side_by_side`'s ``after``), or
    else when its value is first asked for. An exception it raises is kept and raised again to
    whoever asks for the value, as where the computation had run there; ``seconds`` is its own
    duration."""

    def __init__(self, compute: Callable[[], object]):
        import threading

        self._compute = compute
        self._lock = threading.Lock()
        self._done = False
        self._value = self._error = None
        self._thread = None
        self.seconds = 0.0

    def run(self) -> None:
        with self._lock:
            if self._done:
                return
            started = time.monotonic()
            try:
                self._value = self._compute()
            except Exception as err:  # raised again by value(), where the caller handles it
                self._error = err
            self.seconds = time.monotonic() - started
            self._done = True

    def start(self) -> None:
        """:meth:`run` on a thread of its own, now (:meth:`wait` and :meth:`value` wait for it)."""
        import threading

        self._thread = threading.Thread(target=self.run, name="pisml-deferred", daemon=True)
        self._thread.start()

    def wait(self) -> None:
        """Until :meth:`start`'s thread has ended (at once where it was not started)."""
        if self._thread is not None:
            self._thread.join()

    def value(self):
        self.run()
        if self._error is not None:
            raise self._error
        return self._value


class _StoppedBeside(Exception):
    """Raised in a job of :func:`_side_by_side` when another job failed or the run was cancelled."""


def _stability_anchors(train: Dataset, smallsignal: Dataset | None, cfg: IdentConfig) -> list:
    """The records whose rest states anchor the refinement's stability and equilibrium priors."""
    records = list(smallsignal) if smallsignal is not None else []
    return records + list(train) if cfg.refine_stability_points == "records" else records


def _integrators_restricted(model: ExplicitModel, cfg: IdentConfig, train: Dataset | None = None) -> ExplicitModel:
    """``model`` with its integrator equations kept to the terms :func:`~.library.integrator_row_mask`
    admits (``cfg.integrator_terms`` "linear", "error" or "cascade") and its output filter's equations to those
    :func:`~.library.filter_row_mask` admits (``cfg.filter_terms == "physics"``), its filtered-power
    equations to those :func:`~.library.power_row_mask` admits (``cfg.power_terms == "physics"``) and
    its grid-current equations' voltage pairs tied (``cfg.filter_voltage_tie``); else ``model`` itself."""
    if cfg.integrator_terms == "any" and cfg.filter_terms != "physics" and cfg.power_terms != "physics":
        return model
    signals = list(model.state_names) + list(model.input_names)
    mask = np.ones(model.coefficients.shape, dtype=bool)
    meta = dict(model.metadata)
    if cfg.integrator_terms != "any":
        mask &= integrator_row_mask(model.terms, list(model.state_names), signals, cfg.roles,
                                    own_loop=cfg.integrator_terms == "linear",
                                    inner_loops=cfg.integrator_terms != "cascade")
        meta["integrator_terms"] = cfg.integrator_terms
    coef = np.where(mask, model.coefficients, 0.0)
    if train is not None:
        # the filter's and the power's rows are disjoint: one re-fit over the records serves both
        allowed = np.ones(coef.shape, dtype=bool)
        if cfg.filter_terms == "physics":
            allowed &= filter_row_mask(model.terms, list(model.state_names), signals, cfg.roles)
            meta["filter_terms"] = "physics"
        if cfg.power_terms == "physics":
            allowed &= power_row_mask(model.terms, list(model.state_names), signals, cfg.roles)
            meta["power_terms"] = "physics"
        if not allowed.all():
            coef = _rows_refitted(model, coef, allowed, train)
    restricted = ExplicitModel(model.state_names, model.input_names, model.terms, coef, meta)
    if cfg.filter_terms == "physics" and cfg.filter_voltage_tie > 0 and train is not None:
        return _grid_voltage_tied(restricted, cfg.roles, train, cfg.filter_voltage_tie)
    return restricted


def _grid_voltage_tied(model: ExplicitModel, roles: SignalRoles, train: Dataset, tolerance: float) -> ExplicitModel:
    """``model`` with each grid-current row's voltage and grid term merged into one term, the
    voltage across the grid-side inductor (:func:`~.library.grid_voltage_pairs`), where the row's
    two coefficients are already equal and opposite within ``tolerance`` (relative); the row
    re-fitted to its own field over the records' samples.

    Both voltages sit near 1 p.u. at every point the records visit, so a fit sets each coefficient
    (~wb/Lg, 7500 1/s) only to its noise, and their mismatch is a bias of the row: at 40 dB,
    recording 39's model had 7506 and −7503, a field of 2.9 1/s in ig_d at the plant's own
    equilibrium (``IdentConfig.filter_voltage_tie`` for why this is not the IOD misses' cause).
    """
    signals = list(model.state_names) + list(model.input_names)
    pairs = grid_voltage_pairs(model.terms, model.state_names, signals, roles)
    coef = model.coefficients
    ties = []
    for row, kv, kg, sign, tie in pairs:
        a, b = coef[kv, row], sign * coef[kg, row]  # the coefficients of v and of the grid voltage
        if a != 0 and b != 0 and abs(a + b) <= tolerance * max(abs(a), abs(b)):
            ties.append((row, kv, kg, tie))
    if not ties:
        return model
    terms = list(model.terms)
    for tie in dict.fromkeys(t for *_, t in ties):
        if tie not in terms:
            terms.append(tie)
    coef = np.vstack([coef, np.zeros((len(terms) - len(model.terms), model.n_states))])
    allowed = np.ones(coef.shape, dtype=bool)
    for row, kv, kg, tie in ties:
        allowed[:, row] = coef[:, row] != 0
        allowed[[kv, kg], row] = False
        allowed[terms.index(tie), row] = True
    wide = ExplicitModel(model.state_names, model.input_names, terms, coef, model.metadata)
    refitted = _rows_refitted(wide, coef, allowed, train)
    meta = dict(model.metadata, filter_voltage_tie=[model.state_names[row] for row, *_ in ties])
    return ExplicitModel(model.state_names, model.input_names, terms, refitted, meta)


def _rows_refitted(model: ExplicitModel, coef: np.ndarray, allowed: np.ndarray, train: Dataset) -> np.ndarray:
    """``coef`` (over ``model``'s terms) with each row that meets a term ``allowed`` bars kept to
    the terms it admits (the output filter's rows to :func:`~.library.filter_row_mask`'s, …), those
    re-fitted (least squares over the records' samples) to the row's own field.

    The dropped terms stood in for the kept ones where the records are (collinear there): the
    re-fit keeps what the rows learned where the data are and drops what they extrapolate. A re-fit
    on the records' derivatives (equation error, noise-compensated) started 2 of 11 refinements at
    an unstable LCL mode (+2000 1/s) at 40 dB and lost every 40 dB target there (stop 44).
    """
    signals = list(model.state_names) + list(model.input_names)
    z = np.concatenate([np.hstack([tr.x, tr.u]) for tr in train])
    theta = term_set(model.terms, signals).evaluate(z)
    out = coef.copy()
    for j in range(model.n_states):
        if allowed[:, j].all():
            continue
        cols = np.flatnonzero(allowed[:, j])
        out[:, j] = 0.0
        out[cols, j] = np.linalg.lstsq(theta[:, cols], theta @ coef[:, j], rcond=None)[0]
    return out


def frequency_centre(train: Dataset, frequency: str) -> float:
    """Where the frequency state sits at rest: the median of its rest values over the records that
    start at rest (the droop power state's set-point), else its mean over every sample."""
    column = list(train.state_names).index(frequency)
    rests = [rest[column] for tr in train for _, rest in [steady_start_mean(tr)] if rest is not None]
    values = rests or [float(np.mean(np.concatenate([tr.x[:, column] for tr in train])))]
    return float(np.median(values))


def _couplings_centred(model: ExplicitModel, cfg: IdentConfig, train: Dataset) -> ExplicitModel:
    """``model`` with its products of the frequency state written about its rest value
    (:func:`~.library.centred_terms`; ``cfg.refine_centred_couplings``), the same vector field.

    The refinement then fits, and its pruning drops, ``(Pf - P0)*s`` and ``s`` as separate effects:
    with ``Pf*s`` (≈ ``P0*s`` at every rest point) the pruning could drop ``s`` itself at no cost and
    keep the product as its stand-in — at 40 dB it dropped ``il_d`` from the grid-current rows and
    kept ``Pf*il_d`` and ``Pf*ig_d`` at ±540.
    """
    frequency = cfg.roles.frequency
    if not (cfg.refine_centred_couplings and frequency in model.state_names and _noisy(train)):
        return model
    signals = list(model.state_names) + list(model.input_names)
    centre = round(frequency_centre(train, frequency), 4)
    centred = centred_terms(model.terms, signals, frequency, centre)
    if centred == list(model.terms):
        return model
    # the deviation products bring their plain factors (il_d from (Pf - P0)*il_d)
    needed, _ = monomial_basis([t for t, c in zip(centred, model.terms) if t != c], signals)
    plain, _ = monomial_basis(model.terms, signals)
    terms = centred + [m for m in needed if m not in plain and m not in centred]
    coef = rebased(model.terms, model.coefficients, terms, signals)
    used = np.any(coef != 0, axis=1)
    meta = {**model.metadata, "centred_couplings": {"signal": frequency, "centre": centre}}
    return ExplicitModel(model.state_names, model.input_names, [t for t, keep in zip(terms, used) if keep],
                         coef[used], meta)


#: training error (%) from which a candidate is no refinement start: its free run is further from the
#: records than a model that predicts zero
HOPELESS_ERROR_PCT = 100.0


def _refinement_starts(candidates: dict, scores: dict, points: list, verdicts: dict | None = None) -> list:
    """The candidates the refinement starts from: the best-scoring merged (``distilled``) or
    re-fitted (``re-fit …``) one with an equilibrium at every operating point in ``points`` (any, if
    none has) among those scoring below :data:`HOPELESS_ERROR_PCT` (the merged model, if none does;
    all, if there is none), and the noise-compensated backbone where there is one with such equilibria.

    Measured at 80 and 100 dB SNR: re-fits that lost integrator terms scored best (0.04-0.5 %) but
    had no equilibrium, and the refinement from them was abandoned; from the merged model it
    reached 0.03 / 0.04 % (100 dB) and 0.34 / 0.75 % (80 dB) IOD/OOD. At 40 dB neither start wins
    everywhere (pruned refinements, IOD / OOD % on the test records; recordings 0, 1, 2 of the
    benchmark, the demo recording): from the merged model 0.32 / 0.51, 0.29 / 0.49, 0.47 / 2.13,
    failed (training error 3.0 %, W ~1500); from the noise-compensated backbone (its LCL part is
    the better one) 0.34 / 0.35, 1.20 / 3.77, 0.53 / 0.76, 0.24 / 0.48. Each start's refinement
    is a family of candidates (``"refined"``, ``"pruned +B %"``; ``… from <start>`` for the second,
    and for the clean-data fallback's ``… from distilled``, ``PISML._clean_growing_fallback``)
    and the selection takes the one that reproduces the training and small-signal records best.
    """
    verdicts = {} if verdicts is None else verdicts
    names = [name for name in candidates if name == "distilled" or name.startswith("re-fit")]
    # a candidate whose free run is further from the records than zero is (HOPELESS_ERROR_PCT) is no
    # start, equilibria or not. Measured (stop 51, protocol recording 9 with records of 80 ms, 40 dB):
    # the merged model lacked an equilibrium at a rest point and the re-fits scored 276-483 %; the
    # refinement from the best re-fit stalled at 45 %, and the noise-compensated backbone was chosen
    # unrefined (12.2 %, "not to be trusted"); from the merged model 0.26 / 0.21 % IOD / OOD
    useful = [name for name in names if scores[name] < HOPELESS_ERROR_PCT]
    if not useful:
        # every free run that far off: the merged model (the whole library's field), equilibria or not.
        # Measured (stop 98, unseen protocol recording 357 at 40 dB): the merged model ran away (score
        # inf, no equilibria), the re-fits scored 337-1e12 %; the start the equilibria chose, the
        # 337 % re-fit, refined to 34-60 % IOD and the fit kept the noise-compensated backbone (3.98 /
        # 4.54 % IOD / OOD); from the merged model 0.30 / 0.50 % with 60 coefficients
        useful = ["distilled"] if "distilled" in names else names
    eligible = _with_equilibria(useful, candidates, scores, points, verdicts)
    starts = [min(eligible or useful, key=lambda name: scores[name])]
    starts += _with_equilibria([name for name in candidates if name == NOISE_COMPENSATED],
                               candidates, scores, points, verdicts)
    return starts


def _sparse_refits(merged: ExplicitModel, library: list, train: Dataset, cfg: IdentConfig) -> dict:
    """Candidates ``"re-fit +B %"``: all of ``library`` fitted jointly on ``train`` and made sparse
    (:func:`~.refit.sparse_refit`), one per ``cfg.refit_budgets`` entry B; metadata from ``merged``."""
    from .refit import sparse_refit

    if not cfg.refit_budgets:
        return {}
    try:
        fits = sparse_refit(train, library, cfg.refit_budgets, span=cfg.refit_span)
    except (ValueError, np.linalg.LinAlgError) as err:
        # too little data for the library: the other candidates stand
        merged.metadata.setdefault("refit_errors", []).append(f"{type(err).__name__}: {err}")
        return {}
    out = {}
    for budget, coef in zip(cfg.refit_budgets, fits):
        used = np.any(coef != 0, axis=1)
        out[f"re-fit +{100 * budget:g} %"] = ExplicitModel(
            merged.state_names, merged.input_names, [t for t, keep in zip(library, used) if keep], coef[used],
            {**merged.metadata, "stage": "re-fit", "refit": {"budget": budget, "span": cfg.refit_span}})
    return out


def _with_terms(model: ExplicitModel, terms: list, train: Dataset, span: int, refit: bool = True) -> ExplicitModel:
    """``model`` with ``terms`` added to every equation: each equation's own terms and ``terms``
    fitted jointly in integral form over windows of ``span`` samples (least squares); without
    ``refit``, ``terms`` alone fitted to what ``model`` leaves, its own coefficients kept."""
    from .derivatives import integral_form

    signals = list(model.state_names) + list(model.input_names)
    extra = [t for t in terms if t not in model.terms]
    all_terms = [*model.terms, *extra]
    a, b = integral_form(train, term_set(all_terms, signals), span=span)
    coef = np.zeros((len(all_terms), len(model.state_names)))
    added = list(range(len(model.terms), len(all_terms)))
    for j in range(len(model.state_names)):
        if refit:
            support = [*np.flatnonzero(model.coefficients[:, j]), *added]
            coef[support, j] = np.linalg.lstsq(a[:, support], b[:, j], rcond=None)[0]
        else:
            coef[:len(model.terms), j] = model.coefficients[:, j]
            left = b[:, j] - a[:, :len(model.terms)] @ model.coefficients[:, j]
            coef[added, j] = np.linalg.lstsq(a[:, added], left, rcond=None)[0]
    return ExplicitModel(model.state_names, model.input_names, all_terms, coef,
                         {**model.metadata, "stage": "with added terms"})


def _noisy(train: Dataset, level: float = 1e-5) -> bool:
    """Whether the measured noise (relative to each state's spread) is worth compensating."""
    from .noise import estimate_noise_std

    spread = np.concatenate([tr.x for tr in train]).std(axis=0)
    return bool(np.max(estimate_noise_std(train) / np.maximum(spread, 1e-12)) > level)


def _ridge_weight(train: Dataset, cfg: IdentConfig) -> float:
    """The refinement's ridge prior weight (``cfg.refine_ridge_weight``) on noisy records, 0 on clean
    ones: it is there to drop the pairs of terms that cancel along noisy records, and clean records
    pin their coefficients without it (its measurements were all on 40 dB data)."""
    return cfg.refine_ridge_weight if _noisy(train) else 0.0


def _hybrid_model(field, train: Dataset, theta_terms: list, backbone: ExplicitModel) -> tuple:
    """``(trained backbone, hybrid model)`` of a trained HybridField: Θ with the field's Ξ (the backbone's
    metadata), and the field as a model with the records' rest points."""
    from .neural import NeuralModel

    trained = ExplicitModel(train.state_names, train.input_names, theta_terms,
                            field.coefficients().detach().numpy().copy(), dict(backbone.metadata))
    return trained, NeuralModel(field, train.state_names, train.input_names, reference_points(train),
                                backbone=trained, kind="hybrid")


def _distilled(hybrid, trained: ExplicitModel, train: Dataset, ext: list, signals: list,
               cfg: IdentConfig) -> ExplicitModel:
    """The hybrid's residual sampled on and around the training envelope (``cfg.seed``), fitted over the
    extended library ``ext`` by sparse regression and merged with the ``trained`` backbone."""
    from .distill import distill_residual, merge, sample_envelope

    xs, us = sample_envelope(train, cfg.distill_samples, cfg.distill_spread, seed=cfg.seed)
    basis, coef = distill_residual(hybrid.residual, xs, us, ext, signals, cfg.distill_threshold,
                                   max_terms=cfg.distill_max_terms)
    return merge(trained, basis, coef, {"stage": "distilled"})


def _train_field(est: _Estimator, train: Dataset, smallsignal, backbone: ExplicitModel | None, lambda_pert: float,
                 config: IdentConfig | None = None, report: Callable | None = None, history: str = "training"):
    """Build and train a HybridField (backbone optional) with ``config`` (default: the estimator's);
    ``report(epoch, losses)`` replaces the estimator's progress reports, ``history`` names the
    training's entry in ``est.history_``."""
    from .neural import StopRequested, build_modules, resolve_device, train_hybrid

    cfg = config or est.config
    residual_cls, hybrid_cls = build_modules()
    # the initial weights too come from the seed, so that a fit is reproducible (before, the 40 dB
    # benchmark recording's trained backbone scored 2.920, 2.951, 2.957 % in three runs, and the
    # explicit model came out at 0.29 / 0.41 % in one run, 0.36 / 0.76 % in another)
    import torch

    torch.manual_seed(cfg.seed)
    z = np.concatenate([np.concatenate([tr.x, tr.u], 1) for tr in train])
    n_x = len(train.state_names)
    # output scale: the typical size of each state's derivative (from finite differences of the data)
    dz = np.concatenate([np.diff(tr.x, axis=0) / train.dt for tr in train])
    out_scale = np.std(dz, axis=0) + 1e-9
    if backbone is not None:
        out_scale = 0.1 * out_scale  # the backbone carries most of the field; N learns what it misses
    # dropout only in PISML's residual: the paper's Pure NODE has none
    mlp = residual_cls(z.shape[1], n_x, tuple(cfg.hidden), cfg.dropout if backbone is not None else 0.0,
                       z.mean(axis=0), z.std(axis=0) + 1e-9, out_scale)
    signals = list(train.state_names) + list(train.input_names)
    if backbone is not None:
        field = hybrid_cls(backbone.terms, signals, n_x, xi0=backbone.coefficients, mlp=mlp)
    else:
        field = hybrid_cls(None, signals, n_x, mlp=mlp)
    state_scale = z[:, :n_x].std(axis=0) + 1e-9

    device = resolve_device(cfg.device)
    est.metrics_["training_on_gpu"] = float(device.startswith("cuda"))

    if backbone is not None:
        schedule = dict(epochs=cfg.epochs, learning_rate=cfg.learning_rate, weight_decay=cfg.weight_decay,
                        lr_schedule=cfg.lr_schedule, full_passes=False)
    else:  # the Pure NODE baseline, as the paper trains it
        schedule = dict(epochs=cfg.node_epochs, learning_rate=cfg.node_learning_rate,
                        weight_decay=cfg.node_weight_decay, lr_schedule="onecycle", full_passes=True)
    epochs = schedule["epochs"]

    def progress(epoch, losses):
        if epoch % 5 == 0 or epoch == epochs - 1:
            if report is not None:
                report(epoch, losses)
            else:
                est._emit("training", min(0.6, 0.05 + 0.55 * (epoch + 1) / epochs), epoch=epoch, losses=losses)

    try:
        trained = train_hybrid(field, train, smallsignal, window=cfg.window, batch_windows=cfg.batch_windows,
                               lambda_pert=lambda_pert, lambda_sparse=cfg.lambda_sparse if backbone else 0.0,
                               solver=cfg.solver, substeps=cfg.substeps, adjoint=cfg.adjoint, seed=cfg.seed,
                               state_scale=state_scale, callback=progress, should_stop=est._should_stop,
                               device=device, **schedule)
    except StopRequested:
        raise IdentificationCancelled(f"{est.method}: cancelled during training") from None
    est.history_[history] = trained.to_dict()
    if history == "training":
        est.metrics_["final_trajectory_loss"] = trained.trajectory_loss[-1] if trained.trajectory_loss else float("nan")
    return field


def training_error(model, train: Dataset) -> float:
    """ε (%) over all states of free-run simulations of the training records (inf if one diverges).

    A record that starts at rest is run from the mean of its steady start, not from its first
    sample: on noisy data the first sample's noise, propagated through 40 ms of slow dynamics, made
    the error rank models by how they carry that noise. Measured (benchmark's 40 dB recording, five
    candidates): from the first samples the pruned refinement scored 7.06 % against the
    noise-compensated backbone's 3.75 %, from the rest means 1.59 % against 2.37 % — the order of
    their errors against the clean truth (0.62 / 1.63 %) and on the test set (0.37 / 1.63 % IOD).
    """
    return training_errors({0: model}, train)[0]


def training_errors(models: dict, train: Dataset, known: dict | None = None) -> dict:
    """:func:`training_error` of each of ``models`` (by key). Explicit models over the same terms,
    states and inputs (a refinement's family, say) run in one vectorised simulation: a free run is
    a few thousand small vector-field calls whose cost is per call, not per row (measured: ~0.7 s
    per model on the 40 dB benchmark's training + small-signal records). ``known``: errors already
    had, by key, taken as they are (in the order the keys would have had)."""
    from ..analysis.metrics import relative_error

    known = known or {}
    started = _rest_started(train)
    groups: dict = {}
    for key, model in models.items():
        shared = (tuple(model.terms), tuple(model.state_names), tuple(model.input_names)) \
            if isinstance(model, ExplicitModel) and not model.hidden_state_names else ("single", key)
        groups.setdefault(shared, []).append(key)
    out = {}
    for group in groups.values():
        out.update({key: known[key] if key in known else None for key in group})
        keys = [key for key in group if key not in known]
        if not keys:
            continue
        system = models[keys[0]] if len(keys) == 1 else _Stacked([models[k] for k in keys])
        try:
            pred = system.simulate(started)
        except (FloatingPointError, ValueError):
            out.update({k: float("inf") for k in keys})
            continue
        for i, key in enumerate(keys):
            with np.errstate(over="ignore"):  # a run that blew up scores inf
                errs = [relative_error(p.x, t.x)
                        for p, t in zip(pred.trajectories[i * len(train):(i + 1) * len(train)], train)]
            out[key] = float(np.mean(errs)) if np.all(np.isfinite(errs)) else float("inf")
    return out


def hold_error(train: Dataset) -> float:
    """The :func:`training_error` of holding each record's first state (its rest mean where it starts
    at rest): what a model must beat to say anything about the dynamics (~40 % on the protocol's
    training and small-signal records, clean or at 40 dB)."""
    from ..analysis.metrics import relative_error

    return float(np.mean([relative_error(np.repeat(start.x[:1], len(tr), axis=0), tr.x)
                          for start, tr in zip(_rest_started(train), train)]))


class _Stacked:
    """Explicit models over the same terms, simulated together: :meth:`simulate` replays the records
    once per model (model-major), and the vector field applies each model's coefficients to its own
    block of rows."""

    def __init__(self, models: list):
        self.models = models
        self.state_names, self.input_names = models[0].state_names, models[0].input_names
        self.coefficients = np.stack([m.coefficients for m in models])  # (K, n_terms, n_states)

    def vector_field(self, x, u):
        features = self.models[0].features(x, u)  # (K·rows, n_terms), model-major rows
        k = len(self.models)
        return np.matmul(features.reshape(k, -1, features.shape[-1]), self.coefficients).reshape(x.shape)

    def simulate(self, dataset: Dataset) -> Dataset:
        from ..model.replay import replay

        # model-major copies of the records: simulate_many's RK4 runs them all in one pass in list
        # order (the shorter ones held to the longest's length), so every vector-field call sees K
        # equal blocks of rows
        repeated = Dataset(dataset.state_names, dataset.input_names, list(dataset) * len(self.models), dataset.metadata)
        return replay(self, repeated)


def _rest_started(train: Dataset, min_samples: int = 5) -> Dataset:
    """``train`` with the first sample of each record that starts at rest replaced by the mean of
    its steady start (the same on clean data)."""
    from ..data import Trajectory

    trajectories = []
    for tr in train:
        _, rest = steady_start_mean(tr, min_samples)
        if rest is not None:
            x = tr.x.copy()
            x[0] = rest
            tr = Trajectory(tr.traj_id, tr.t, x, tr.u)
        trajectories.append(tr)
    return Dataset(train.state_names, train.input_names, trajectories, train.metadata)


def refine_explicit(model: ExplicitModel, train: Dataset, smallsignal: Dataset | None, cfg: IdentConfig,
                    progress: Callable[[float, dict], None] | None = None, start_error: float | None = None,
                    errors: dict | None = None, scoring: Dataset | None = None, growing: bool | None = None) -> dict:
    """Multiple-shooting least-squares refinement of the nonzero coefficients of ``model``, then
    sparser models by backward elimination on the refinement's quadratic cost model.

    Each budget ``b`` of ``cfg.refine_prune_budgets`` gives the sparsest model whose predicted
    refinement cost is at most (1 + b)× the refined one's (:func:`~.trajfit.backward_elimination`;
    no further integration). The caller selects among them on free-run training error. On noisy
    data, or with ``growing`` (and ``cfg.refine_growing_windows`` set either way), the refinement
    runs in stages of growing windows instead, and the first budget's pruned model is re-fitted
    (:func:`_refine_growing`). RK4 runs with at least ``dt / cfg.refine_max_step`` substeps per
    sample (the metadata's ``rk4_substeps``).

    Parameters
    ----------
    start_error : float, optional
        :func:`training_error` of ``model``, if the caller has it already.
    errors : dict, optional
        Receives the training errors this function computes, by candidate name.
    scoring : Dataset, optional
        The records :func:`training_error` runs on (``start_error`` is on them too); ``train`` if not given.
    growing : bool, optional
        Whether to refine in stages of growing windows; by default on noisy data. Without
        ``cfg.refine_growing_windows`` the one-stage refinement runs whatever this says.

    Returns
    -------
    dict
        ``{"refined": model, "pruned +0.1 %": model, ...}`` (the caller selects).
    """
    from .noise import residual_weights
    from .trajfit import TrajectoryFitter, backward_elimination

    signals = tuple(model.state_names) + tuple(model.input_names)
    weights = residual_weights(train)

    import torch

    # the windows shared out over torch's threads (one where the caller runs fits side by side), at
    # most SHOOTING_PARTS_MAX of them (the parts contend for the GIL)
    threads = min(torch.get_num_threads(), SHOOTING_PARTS_MAX)

    substeps_used: set = set()
    rest_starts = cfg.refine_rest_starts if _noisy(train) else 0.0  # (the prior is for noisy records)

    def make_fitter(window, max_windows, substeps=2, single_precision=False):
        if cfg.refine_max_step > 0:  # coarse samples: RK4's own error would bias the coefficients
            substeps = max(substeps, math.ceil(train.dt / cfg.refine_max_step - 1e-9))
        substeps_used.add(substeps)
        return TrajectoryFitter(term_set(model.terms, signals), model.n_states, train.dt, window=window,
                                substeps=substeps, weights=weights, max_windows=max_windows, threads=threads,
                                single_precision=single_precision, held_levels=cfg.refine_held_levels,
                                rest_starts=rest_starts)

    errors = {} if errors is None else errors
    if cfg.refine_growing_windows and (_noisy(train) if growing is None else growing):
        return _refine_growing(model, train, smallsignal, cfg, make_fitter, progress, substeps_used)
    fitter = make_fitter(cfg.refine_window, cfg.refine_max_windows)
    if start_error is None:
        start_error = training_error(model, train if scoring is None else scoring)
    checked: list = []  # free-run training errors at the accepted points looked at

    def on_evaluation(nfev, cost):
        if progress:
            progress(min(nfev / max(cfg.refine_max_nfev, 1), 1.0),
                     {"refine_cost": cost, "nonzero": int(np.count_nonzero(model.coefficients))})

    def improving(c):
        # a free-run check costs ~1 s; once the fit beats its start it has earned its budget (the
        # selection scores the result anyway)
        if checked and checked[-1] < start_error:
            return True
        checked.append(training_error(ExplicitModel(model.state_names, model.input_names, model.terms, c),
                                      train if scoring is None else scoring))
        return _worth_continuing(checked, start_error)

    try:
        result = fitter.fit(model.coefficients.copy(), model.coefficients != 0, train, smallsignal,
                            lambda_jac=1.0 if smallsignal is not None else 0.0, max_nfev=cfg.refine_max_nfev,
                            on_evaluation=on_evaluation, keep_going=improving, fit_starts_first=True,
                            lambda_stab=cfg.refine_stability_weight, stability_margin=cfg.refine_stability_margin,
                            stability_records=_stability_anchors(train, smallsignal, cfg),
                            lambda_eq=cfg.refine_equilibrium_weight, lambda_ridge=_ridge_weight(train, cfg))
    except (ValueError, np.linalg.LinAlgError, FloatingPointError) as err:
        # a refinement that breaks down (a window blowing up) leaves the earlier candidates standing
        model.metadata.setdefault("refinement_errors", []).append(f"{type(err).__name__}: {err}")
        return {}
    meta = dict(model.metadata)
    meta["refinement"] = {"cost": result.cost, "nfev": result.nfev, "seconds": result.seconds,
                          "abandoned": result.abandoned, "rk4_substeps": sorted(substeps_used)}
    out = {"refined": ExplicitModel(model.state_names, model.input_names, model.terms, result.coefficients,
                                    {**meta, **_with_covariance(result)})}
    if result.abandoned:
        errors["refined"] = checked[-1]  # the abandoned point is the one just checked
        model.metadata.setdefault("refinement_notes", []).append(
            f"abandoned after {result.nfev} evaluations (training error not improving)")
        return out
    budgets = tuple(cfg.refine_prune_budgets)
    if budgets and result.hessian is not None:
        # every equation keeps a term: an empty one freezes its state (no isolated equilibrium)
        pruned = backward_elimination(result.coefficients, result.hessian, result.support,
                                      [b * result.cost for b in budgets], groups=result.support % model.n_states)
        for budget, (rise, coef) in zip(budgets, pruned):
            name = f"pruned +{100 * budget:g} %"
            out[name] = ExplicitModel(model.state_names, model.input_names, model.terms, coef,
                                      {**meta, "pruning": {"budget": budget,
                                                           "predicted_cost_rise": rise / max(result.cost, 1e-300)}})
    return out


def _merge_pass(into: tuple, second: tuple, unrefined: set, suffix: str) -> None:
    """The candidates (and their scores) a second refinement pass added to ``unrefined``'s, renamed with
    ``suffix``, into the first pass's ``(candidates, scores)``. (Rest-point verdicts are cached by name
    and kind: the selection finds the renamed ones again.)"""
    for name in second[0]:
        if name not in unrefined:
            for mine, theirs in zip(into, second):
                if name in theirs:
                    mine[name + suffix] = theirs[name]


def low_snr(train: Dataset, cfg: IdentConfig) -> bool:
    """Whether ``train`` counts as low-SNR records: its estimated signal-to-noise ratio
    (:func:`.noise.estimated_snr_db`) below ``cfg.low_snr_below_db`` (dB)."""
    return bool(estimated_snr_db(train) < cfg.low_snr_below_db)


def refinement_passes(train: Dataset, cfg: IdentConfig) -> list:
    """The refinement's passes on ``train``: ``(config, suffix)`` each, the suffix ending the names of the
    pass's candidates. One, ``cfg`` itself; on noisy low-SNR records (:func:`low_snr`) with
    ``cfg.refine_growing_windows_low_snr`` set, a second pass whose growing stages are those windows, with
    ``cfg.refine_growing_evaluations_low_snr`` (or ``cfg.refine_growing_evaluations``) and every window,
    and no limit search (the first pass's stands)."""
    if not (cfg.refine_growing_windows_low_snr and _noisy(train) and low_snr(train, cfg)):
        return [(cfg, "")]
    second = dataclasses.replace(
        cfg, refine_growing_windows=cfg.refine_growing_windows_low_snr,
        refine_growing_evaluations=cfg.refine_growing_evaluations_low_snr or cfg.refine_growing_evaluations,
        refine_growing_max_windows=(), limiter_search=False)
    return [(cfg, ""), (second, LOW_SNR_SUFFIX)]


def _refine_growing(model: ExplicitModel, train: Dataset, smallsignal: Dataset | None, cfg: IdentConfig,
                    make_fitter, progress=None, substeps_used: set | None = None) -> dict:
    """The noisy-data refinement (and clean data's where no candidate reproduces them,
    ``IdentConfig.clean_growing_error``): stages of growing windows over all the data, then the model pruned
    at the first of ``cfg.refine_prune_budgets`` re-fitted in stages of its own, and pruned and
    re-fitted again for ``cfg.refine_prune_rounds`` rounds in all (one candidate per round).

    From a far-off start on noisy data, short windows keep the fit near the data (every window
    starts at fitted states) while the coefficients move a long way; longer windows then
    average the noise over more samples and pin what short ones cannot (the LCL and slow parts).
    Straight to long windows such a fit diverges or stalls in a poor minimum; the one-stage
    refinement is abandoned there (its free-run error does not fall).

    Returns
    -------
    dict
        ``{"refined": model, "pruned +B %": model, "pruned +B % x2": model, ...}`` (the caller selects).
    """
    from .trajfit import START_DAMPING, backward_elimination

    stages = list(zip(cfg.refine_growing_windows, cfg.refine_growing_evaluations))
    polish = list(zip(cfg.refine_polish_windows, cfg.refine_polish_evaluations))
    # a later prune round starts next to a minimum of a wider support: the longest windows suffice
    repolish = polish[-1:]
    total = sum(n for _, n in stages + polish) + (cfg.refine_prune_rounds - 1) * sum(n for _, n in repolish)
    if cfg.refine_long_branch and repolish:
        total += cfg.refine_long_branch_evaluations + cfg.refine_prune_rounds * sum(n for _, n in repolish)
    done, used = [0], [0]  # evaluations budgeted (progress) and spent
    lambda_jac = 1.0 if smallsignal is not None else 0.0
    # with a degree preference above 1 the rounds drop higher-degree terms ahead of lower-degree
    # ones that cost as little to lose (IdentConfig.refine_prune_degree_preference)
    degrees = term_degrees(model.terms, tuple(model.state_names) + tuple(model.input_names))
    order_weights = cfg.refine_prune_degree_preference ** -(degrees - 1.0)
    ridge_weight = _ridge_weight(train, cfg)
    # the terms' state gradients at the records' rest states: the pruning keeps a coefficient whose drop
    # would leave a mode that does not pull back at every one of them (IdentConfig.refine_prune_zero_mode)
    rest_gradients = [model.term_gradients(np.asarray(point["state"], float),
                                           np.asarray(point["inputs"], float))[:, :model.n_states]
                      for point in (model.metadata.get("reference_points") or [])] \
        if cfg.refine_prune_zero_mode > 0 else []

    def run(coef, schedule, lambda_stab=0.0, substeps=2, stage_budget=0.0, rest_weight=0.0, log=None,
            damping=START_DAMPING, single_stages=0, max_windows=()):
        """The trajectory fits of ``schedule`` one after the other; ``log`` gets a record per stage
        (window, support, evaluations, accepted steps, wall seconds, cost): where a fit's time goes."""
        result = None
        for stage, (window, evaluations) in enumerate(schedule):
            if stage and stage_budget > 0 and result is not None and result.hessian is not None:
                # the terms the last stage's fit can spare go before the longer (costlier) windows
                coef = backward_elimination(result.coefficients, result.hessian, result.support,
                                            [stage_budget * result.cost], groups=result.support % model.n_states)[0][1]
                pruned_between.append(int(np.count_nonzero(coef)))
            most = max_windows[stage] if stage < len(max_windows) and max_windows[stage] > 0 else None
            fitter = make_fitter(window, most, substeps, single_precision=stage < single_stages)
            offset = done[0]

            def on_evaluation(nfev, cost):
                if progress:
                    progress(min((offset + nfev) / max(total, 1), 1.0),
                             {"refine_cost": cost, "refine_window": window, "nonzero": int(np.count_nonzero(coef))})

            stage_started = time.monotonic()
            try:
                result = fitter.fit(coef, coef != 0, train, smallsignal, lambda_jac=lambda_jac, max_nfev=evaluations,
                                    on_evaluation=on_evaluation, fit_starts_first=True,
                                    lambda_stab=lambda_stab, stability_margin=cfg.refine_stability_margin,
                                    stability_records=_stability_anchors(train, smallsignal, cfg),
                                    lambda_eq=rest_weight or cfg.refine_equilibrium_weight,
                                    equilibrium_space="states" if rest_weight else "rates",
                                    ftol=cfg.refine_stage_tolerance, lambda_ridge=ridge_weight, damping=damping)
            except ValueError as err:  # no trajectory as long as the window: stop growing
                model.metadata.setdefault("refinement_notes", []).append(f"window {window}: {err}")
                break
            done[0] += evaluations
            used[0] += result.nfev
            if log is not None:
                log.append({"window": window, "windows": result.windows, "support": int(np.count_nonzero(coef)),
                            "evaluations": result.nfev,
                            "accepted": result.accepted, "seconds": round(time.monotonic() - stage_started, 3),
                            "cost": result.cost})
            coef = result.coefficients
        return result

    meta = dict(model.metadata)
    started = time.monotonic()
    pruned_between: list = []  # support sizes after each between-stage pruning
    growing_log: list = []
    try:
        result = run(model.coefficients.copy(), stages, cfg.refine_growing_stability_weight,
                     substeps=cfg.refine_growing_substeps, stage_budget=cfg.refine_stage_prune_budget, log=growing_log,
                     single_stages=cfg.refine_single_precision_stages, max_windows=cfg.refine_growing_max_windows)
    except (np.linalg.LinAlgError, FloatingPointError) as err:
        model.metadata.setdefault("refinement_errors", []).append(f"{type(err).__name__}: {err}")
        return {}
    if result is None:
        return {}
    schedule = {"windows": [w for w, _ in stages], "evaluations": [n for _, n in stages],
                "pruned_between": pruned_between, "stability_weight": cfg.refine_growing_stability_weight}
    if cfg.refine_growing_max_windows:
        schedule["max_windows"] = list(cfg.refine_growing_max_windows)
    meta["refinement"] = {"cost": result.cost, "nfev": used[0], "seconds": time.monotonic() - started,
                          "abandoned": False, "growing_windows": schedule, "rk4_substeps": sorted(substeps_used or ()),
                          "stages": growing_log}
    out = {"refined": ExplicitModel(model.state_names, model.input_names, model.terms, result.coefficients,
                                    {**meta, **_with_covariance(result)})}
    if not cfg.refine_prune_budgets or result.hessian is None:
        return out
    samples = train.n_samples
    # a fraction of the cost for the reference number of samples (IdentConfig.refine_prune_reference_samples)
    budget = cfg.refine_prune_budgets[0] * (cfg.refine_prune_reference_samples / max(samples, 1)
                                            if cfg.refine_prune_reference_samples > 0 else 1.0)

    def prune_rounds(first, polish, repolish, suffix):
        """Prune-and-polish rounds from the fit ``first`` (round 1 re-fitted in ``polish``, later rounds
        in ``repolish``), their candidates named with ``suffix``; returns the last polished fit."""
        polished = first
        for round_ in range(1, cfg.refine_prune_rounds + 1):
            # each round prunes the last round's polished model (its quadratic cost model is taken at a
            # minimum of its own support, unlike the first round's)
            if polished is None or polished.hessian is None:
                break
            base = polished
            # every equation keeps a term: an empty one freezes its state (no isolated equilibrium)
            rise, coef = backward_elimination(base.coefficients, base.hessian, base.support, [budget * base.cost],
                                              order_weights[base.support // model.n_states],
                                              groups=base.support % model.n_states,
                                              state_gradients=rest_gradients, zero_mode=cfg.refine_prune_zero_mode)[0]
            if round_ > 1 and np.count_nonzero(coef) == np.count_nonzero(base.coefficients):
                break  # nothing more to drop: another polish would re-fit the same support
            polish_started, polish_used = time.monotonic(), used[0]
            schedule = polish if round_ == 1 else repolish
            polish_log: list = []
            try:
                polished = run(coef, schedule, cfg.refine_stability_weight, rest_weight=cfg.refine_rest_weight,
                               log=polish_log, damping=cfg.refine_polish_damping) if schedule else None
            except (np.linalg.LinAlgError, FloatingPointError) as err:
                model.metadata.setdefault("refinement_errors", []).append(f"polish: {type(err).__name__}: {err}")
                polished = None
            pruning = {"budget": budget, "nominal_budget": cfg.refine_prune_budgets[0], "training_samples": samples,
                       "reference_samples": cfg.refine_prune_reference_samples,
                       "round": round_, "predicted_cost_rise": rise / max(base.cost, 1e-300),
                       "polish_windows": [w for w, _ in schedule],
                       "polish_cost": None if polished is None else polished.cost,
                       "polish_evaluations": used[0] - polish_used, "polish_seconds": time.monotonic() - polish_started,
                       "polish_rest_weight": cfg.refine_rest_weight, "rk4_substeps": sorted(substeps_used or ()),
                       "polish_stages": polish_log}
            # named by the nominal budget: the same names whatever the records' length
            name = _prune_round_name(f"{100 * cfg.refine_prune_budgets[0]:g}", round_, suffix)
            out[name] = ExplicitModel(model.state_names, model.input_names, model.terms,
                                      coef if polished is None else polished.coefficients,
                                      {**meta, "pruning": pruning, **_with_covariance(polished)})
        return polished

    polished = prune_rounds(result, polish, repolish, "")
    if cfg.refine_long_branch and repolish:
        # a second branch: the refined model re-fitted in the polish's longest windows first, then
        # pruned and polished there (IdentConfig.refine_long_branch)
        long_log: list = []
        try:
            long = run(result.coefficients, [(repolish[0][0], cfg.refine_long_branch_evaluations)],
                       cfg.refine_growing_stability_weight, substeps=cfg.refine_growing_substeps, log=long_log)
        except (np.linalg.LinAlgError, FloatingPointError) as err:
            model.metadata.setdefault("refinement_errors", []).append(f"long branch: {type(err).__name__}: {err}")
            long = None
        if long is not None:
            out["refined" + LONG_BRANCH_SUFFIX] = ExplicitModel(
                model.state_names, model.input_names, model.terms, long.coefficients,
                # its own stage only: the growing stages are the first family's (bench/fit_time.py)
                {**meta, "refinement": {**meta["refinement"], "stages": long_log, "cost": long.cost},
                 **_with_covariance(long)})
            prune_rounds(long, repolish, repolish, LONG_BRANCH_SUFFIX)
    if progress:  # stages that converged early leave evaluations of their budget unused
        progress(1.0, {"refine_cost": result.cost if polished is None else polished.cost})
    return out


def _with_covariance(result) -> dict:
    """``{"coefficient_covariance": ...}`` (:func:`~pisml_ros.analysis.uncertainty.covariance_metadata`)
    of a trajectory fit's coefficients where it has a Hessian, else empty: the metadata that lets the
    analysis say how far the data pin a stability verdict."""
    from ..analysis.uncertainty import covariance_metadata

    covariance = None if result is None else result.covariance()
    if covariance is None or not np.all(np.isfinite(covariance)):
        return {}
    return {"coefficient_covariance": covariance_metadata(result.coefficients.shape, result.support, covariance)}


def _worth_continuing(errors: list, start_error: float, min_fall: float = 0.02) -> bool:
    """Whether a refinement should go on, from the free-run training errors at its accepted points
    so far (``errors``, newest last) and its start model's (``start_error``).

    On while the newest error beats the start's, or still falls (by ``min_fall``, relative, below
    the best so far): the multiple-shooting cost always decreases, but from a far-off start on noisy
    data the model run freely can stay worse. Measured (benchmark recordings, errors in % at the
    first accepted points): 40 dB, start 4.39: 5.57, 5.41, 5.63, 6.01, 5.48, 5.43, 5.16 (never
    better; stopped at the 3rd); 60 dB, start 1.66: 2.93, 2.14, 1.81, 1.32, ... (worse at first,
    falling, then better: it went on to 0.61 / 0.67 % IOD/OOD where its backbones score 2.5-2.9 %).
    """
    newest = errors[-1]
    if newest < start_error:
        return True
    return len(errors) == 1 or newest < (1 - min_fall) * min(errors[:-1])


def make_estimator(method: str = "pisml", config: IdentConfig | None = None):
    """An estimator for ``method`` (one of :data:`METHODS`)."""
    if method == "pisml":
        return PISML(config, use_jacobian=True)
    if method == "pisml-nojac":
        return PISML(config, use_jacobian=False)
    if method == "std-sindy":
        return StdSINDy(config)
    if method == "mod-sindy":
        return ModSINDy(config)
    if method == "node":
        return PureNODE(config)
    raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
