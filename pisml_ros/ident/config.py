"""Settings of the identification engine (one dataclass, loadable from YAML/JSON)."""
from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import Any, Mapping

from .roles import SignalRoles


class ConfigError(ValueError):
    """An unknown or out-of-range identification setting; the message names it."""


def settings_from_assignments(items, where: str = "--set") -> dict:
    """``["epochs=20", "filter_terms=physics"]`` as ``{"epochs": "20", "filter_terms": "physics"}``:
    keys and values stripped, values kept as strings (:meth:`IdentConfig.from_mapping` converts
    them), blank items skipped.

    Raises
    ------
    ConfigError
        For an item without ``=``, named with ``where`` (the option or parameter it came from).
    """
    out = {}
    for item in items:
        if not item or not item.strip():
            continue
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"{where}: {item!r} is not KEY=VALUE")
        out[key.strip()] = value.strip()
    return out


@dataclasses.dataclass
class IdentConfig:
    """All knobs of PISML and the baselines, with the paper's defaults.

    Attributes are grouped by stage: ``backbone_*`` (sparse physics backbone),
    ``hidden``/``dropout``/``epochs``/... (neural residual trained through the ODE
    solver), ``lambda_*`` (loss weights), ``distill_*`` (symbolic distillation), ``refit_*``
    (sparse re-fit of Θ ∪ Θ_ext on the data) and ``refine_*`` (fine-tuning of an explicit
    model on trajectories).
    """

    roles: SignalRoles = dataclasses.field(default_factory=SignalRoles)
    # sparse backbone over Θ, integral (weak) form
    backbone_span: int = 10
    # ... and at most this long (s): at coarser sampling the window holds fewer samples (at least 3),
    # so that it spans the same stretch of the LCL oscillation (period ~0.65 ms) as at the protocol's
    # 10 kHz, where both give 10 samples; 0: backbone_span samples at any rate. Measured (stop 71,
    # scenarios "5 kHz", 40 dB, seeds 0-3, IOD / OOD %): 10 samples (2 ms) gave 0.224 / 0.502,
    # 0.94 / 3.53 (spurious unstable at every ug, W 2140), 0.361 / 1.99, 0.188 / 0.634, two of four
    # within both targets, fits 85-208 s; 5 samples (1 ms) 0.207 / 0.338, 0.614 / 0.370, 0.404 / 0.531,
    # 0.428 / 0.442 (the second with 215 coefficients), three of four, 46-95 s; clean 0.0062 / 0.021
    # and 0.0046 / 0.028 (0.0032 / 0.020, 0.0031 / 0.028). A longer window at 20 kHz (20 samples,
    # 1 ms) was no better: seeds 0 / 1 at 40 dB 0.726 / 0.249 and 0.240 / 0.252 (spurious at ug 0.2,
    # 0.4) against 0.449 / 0.595 and 0.959 / 0.896, hence a bound, not a fixed duration
    backbone_span_max_s: float = 0.001
    backbone_threshold: float = 0.02
    backbone_alpha: float = 1e-6
    # also fit a backbone compensated for the noise in its regressors (backbone.noise_moments), a
    # candidate of the final selection (noisy data only)
    backbone_noise_correction: bool = True
    # the rotating-frame couplings (roles.frequency × dq signals) stay in Θ only when the data
    # separate them from the plain signals at least this well (library.coupling_separation).
    # Measured: 0.08-0.13 (4 records of 20 ms) wreck the backbone with them; a 12 × 40 ms recording
    # at 0.23 (train seed 1) gave 0.31 / 0.40 % IOD/OOD with them and 0.22 / 2.4 % without
    coupling_min_separation: float = 0.2
    # measured inputs with noise in them (ident.noise.input_noise_std > 0; exact steps give 0):
    # "auto" holds them at their means over the stretches where they are constant
    # (ident.noise.piecewise_constant_inputs) before every stage, "off" takes them as given.
    # Measured (stop 49, the protocol's recordings 0-5 with 40 dB on the inputs too): held, IOD
    # 0.52-5.1 %, none diverged; as given, 3.3-17 % or diverged; none within the 40 dB targets
    # either way (README, "Noise on the measured inputs"). Stop 91 pools the held levels where they
    # agree and the refinement takes their errors into account (trajfit.held_level_basis): unseen
    # 240-247 2 of 8 within both targets against 0, IOD median 0.56 against 1.13 %
    input_denoise: str = "auto"
    # with the training records' inputs held (input_denoise above), the trajectory refinement can fit
    # each held level's error beside the coefficients, a parameter shared by every window on that
    # level with the prior N(0, σ²/n) (errors in variables; trajfit.held_window_levels). Measured and
    # not taken (stop 92, bench/setting_sweep.py --scenario "noisy inputs", unseen 240-247 and
    # 280-287): 4 of 16 within both targets with no spurious mode against stop 91's 6, IOD median
    # 0.582 / 0.539 % against 0.561 / 0.545 %, fits median 80 / 84 s against 59 / 71 s (README,
    # "Noise on the measured inputs"); exact inputs (the protocol) hold nothing either way. Why it
    # moves so little (stop 93, recording 286): the windows' data see a level's error with a
    # precision of 0.03-0.18 of the prior's (median over the 36 levels, per refinement stage), so
    # the fitted errors stay near 0 (rms 0.04-0.15 σ/√n against the true 0.91); and a looser prior
    # (3 σ/√n) on 286, 280, 244, 246 gave 0.953 / 0.545, 0.211 / 1.100, 1.416 / 1.659, 0.319 / 0.516 %
    refine_held_levels: bool = False
    # how the held inputs' stretches are found (ident.noise.piecewise_constant_inputs): an inner
    # interval whose mean differs from the rest of its stretch by more than this many standard
    # errors splits it where no single split does (a shallow sag and its recovery; 0: off), and the
    # samples within this many of each step between two held levels take their posterior mean given
    # the step's time (0: off). Measured and not taken (stop 92, 6.0 and 25 with refine_held_levels
    # on, unseen 240-244): 0 of 5 within both targets against 2 of 5 without them (README, "Noise on
    # the measured inputs")
    input_interval_threshold: float = 0.0
    input_edge_width: int = 0
    # neural residual N(x, u) and hybrid training
    hidden: tuple = (128, 128)
    # dropout after each hidden layer of PISML's residual (the paper's Pure NODE has none, nor has
    # ours). The paper's 0.05 is an option, not the default: measured (stop 53, bench/setting_sweep.py,
    # 40 dB protocol recordings 0-4, IOD / OOD %; default 0.158 / 0.438, 0.402 / 0.694, 0.412 / 0.456,
    # 0.329 / 0.497, 0.428 / 0.901, all five within both targets): 0.05 gave 0.269 / 0.861,
    # 0.737 / 1.29 (spurious unstable at ug 1.1), 0.532 / 0.385, 0.636 / 0.832 (149 coefficients),
    # 0.234 / 1.17, one of five. The residual only seeds the distillation and so the first refinement
    # start; a different residual is a different draw of that start, and these were worse ones
    dropout: float = 0.0
    # optimiser steps of the residual's training (an epoch is one batch of windows drawn at random).
    # Measured (stop 53, bench/sweeps/residual-400-batches.json, 40 dB recordings 0-9): 400, about the
    # paper's 50 epochs, gave 5 of 10 within both targets with no spurious mode against 7, <= 84
    # coefficients on 3 against 1, every target on 2 against 1, a spurious mode on recording 5, and a
    # median fit of 70 s against 40: another draw of the first refinement start, not a better one
    epochs: int = 60
    # the optimiser's learning rate (the peak of the "onecycle" schedule)
    learning_rate: float = 1e-3
    # the network's weight decay (AdamW, decoupled; the backbone's Ξ has its L1 penalty instead)
    weight_decay: float = 0.0
    # the learning-rate schedule over the epochs: "cosine" (down to 5 % of learning_rate) or
    # "onecycle" (torch's OneCycleLR, peak learning_rate). The paper's whole recipe for the residual
    # (dropout 0.05, weight_decay 1e-3, onecycle, learning_rate 0.005) measured the same way
    # (recordings 0-6): 0.340 / 0.478 (spurious unstable at ug 0.2, 0.4), 0.730 / 0.345,
    # 0.346 / 0.801, 0.848 / 1.03 (295 coefficients), 0.406 / 1.59, 0.464 / 1.57 (spurious at 0.2),
    # 0.200 / 0.453: two of seven within both targets with no spurious mode, against five
    lr_schedule: str = "cosine"
    # the Pure NODE baseline, trained as the paper's (its Table of settings): AdamW, OneCycle peaking
    # at node_learning_rate, node_epochs passes over every training window (an epoch of PISML's
    # residual above is one batch), the weight decay of the paper's PISML row (none given for NODE).
    # Measured (stop 53, the benchmark's standard plant): clean IOD / OOD 6.89 / 31.4 %, 40 dB
    # 9.89 / 35.8 %, 13-19 s (before, 60 batches at 1e-3 in ~2 s: 36.3 / 54.0 %, 17.7 / 50.6 %)
    node_epochs: int = 50
    node_learning_rate: float = 0.005
    node_weight_decay: float = 1e-3
    window: int = 10
    batch_windows: int = 128
    solver: str = "rk4"
    substeps: int = 1
    adjoint: bool = False
    # where the hybrid trains (torch device): cpu | auto (a CUDA GPU if torch sees one) | cuda[:N];
    # the rest of the pipeline runs on the CPU
    device: str = "cpu"
    lambda_pert: float = 1.0
    lambda_sparse: float = 1e-6
    seed: int = 0
    # on noisy records (not low-SNR ones, low_snr_below_db): how many neural residuals are trained, from
    # seeds seed, seed + 1, ...; each after the first is distilled, re-fitted and refined from its own
    # best start (estimators.PISML._residual_family, no limit search), and its families compete in the
    # selection, named "... (residual 2)". Why (stop 101): which 40 dB fits meet the targets turns on the
    # residual's seed as much as on the noise draw (the same records with seed 1: 32 of the 48 unseen
    # recordings 336-367 and 472-487 within both accuracy targets with no spurious mode, seed 0 27, both 21),
    # and no feature of the records' schedules predicts which (scratch /tmp/s101/design.py: sag depths,
    # pre-event voltages, jump sizes and times, noise floor; none separates hits from misses). Both fits'
    # candidates in one selection (bench/candidates.py --set seed=1 tables pooled with the defaults' and
    # replayed): 33 of 48 against 27, 6 won, none lost (337, 341, 351, 353, 477, 478); a wrong 3-bus or
    # weak-line verdict on 4 of the 48 against 10. Then fitted with it on the unseen 504-511
    # (bench/sweeps/default-unseen-504-511-s101.json): 4 of 8, where the first residual's candidates alone
    # (replayed) give 5 (won 505; lost 504, 0.229 / 0.356 -> 0.670 / 0.469 %, and 511, 0.480 / 0.511 ->
    # 0.444 / 1.914 %); wrong verdicts on 2 of 8 against 5. Over the 56: 37 against 32, 8 won, 2 lost;
    # verdicts wrong on 6 against 15. The cost: a 40 dB fit about doubles (recordings 496 and 501:
    # 54.1 / 53.4 s against 28.6 / 29.4 s; make bench's ten: median 55.4 s against 26.4; 504-511: median
    # 59.3 s, worst 161.9 s, the second residual's rescue on 506)
    residual_fits: int = 2
    # symbolic distillation over Θ_ext
    distill_degree: int = 2
    distill_threshold: float = 0.1
    distill_samples: int = 20000
    distill_max_terms: int = 6
    distill_spread: float = 0.05
    # sparse re-fit of all terms of Θ and Θ_ext on the data (ident.refit; equation error): one
    # candidate per budget (allowed rise of each row's cost over its least-squares minimum); empty: off
    refit_budgets: tuple = (1.0, 3.0, 10.0)
    refit_span: int = 10
    # fine-tuning of the merged explicit model
    refine: bool = True
    refine_window: int = 20
    refine_max_windows: int = 40
    refine_max_nfev: int = 10
    # sparser candidates from the refined model by backward elimination on its quadratic cost model:
    # each allows the refinement cost to rise by this fraction (clean protocol data, two runs: +0.3 %
    # gave 258 → 79 and 257 → 93 coefficients, IOD/OOD 0.037/0.035 and 0.043/0.035 %)
    refine_prune_budgets: tuple = (0.001, 0.003, 0.01)
    # on noisy data: the refinement in stages of growing windows over all the data (window lengths,
    # and evaluations per stage), no early abandonment; then the model pruned at the first prune
    # budget is re-fitted in stages of its own (``refine_polish_*``). Empty: the one-stage refinement
    # above, as on clean data. Measured on the benchmark's 40 dB recording (scratch, from the merged
    # model, 328 coefficients, 81 of the 88 true terms): 5.61 / 5.61 % -> stages 0.86 / 1.26 % ->
    # pruned (167 coefficients) and polished 0.17 / 0.80 %, 160 s; the one-stage refinement was
    # abandoned there. From a start this far, windows of 20-50 samples straight away diverge or stall
    refine_growing_windows: tuple = (10, 25, 50)
    # Evaluations per stage. Stop 30 (40 dB, cost per evaluation logged): with 15 the windows-of-10
    # stage was still falling fast at its last evaluation (recording 0: 3754 there, 2920 at the
    # 30th); its first 4-10 are rejected steps (0.1 s each; an accepted one costs ~1.1 s). Measured
    # (40 dB, IOD / OOD %, coefficients; "ok": both targets): (30, 20, 20), the default since stop 31,
    # benchmark recordings 0-8: 0.16 / 0.44 ok (78), 0.40 / 0.69 ok (90), 0.41 / 0.46 ok (95),
    # 0.90 / 1.43 (149), 0.63 / 0.73 (140), 0.58 / 0.60 (114), 0.52 / 0.64 (93), 0.57 / 0.84 (89),
    # 0.21 / 0.26 ok (107), 88-118 s; (15, 10, 10) before it: 0.28 / 0.44 ok, 0.68 / 0.58,
    # 0.65 / 0.41, 0.57 / 0.32, 0.32 / 1.95, 0.99 / 0.59, 0.81 / 0.37, 0.38 / 0.75 ok, 0.30 / 1.00,
    # 51-70 s. Off the protocol (bench/scenarios_bench.py, seed 1) 15 -> 30: phase jumps 10-20°
    # 0.97 / 3.97 (W 217) -> 0.24 / 0.64 (W 6.1), ug0 0.6-1.0 2.83 / 6.04 (W 1594) -> 0.45 / 0.79
    # (W 5.9), 8 records of 60 ms 0.90 / 2.82 -> 0.56 / 4.09. The longer stages need their 20 as well:
    # (30, 8, 8) on recordings 0-4 0.79 / 1.04, 1.02 / 0.74, 1.03 / 1.67 (spurious at 0.2-0.6),
    # 0.68 / 0.77, 0.35 / 1.09, 69-93 s. Not taken (stop 31, recordings 0-4): windows of 10 over half
    # the windows with 30 evaluations (the time of 15 over all): 0.30 / 0.73, 0.56 / 0.52,
    # 0.58 / 0.74, 0.40 / 0.59, 0.25 / 0.72, 63-81 s; rejected steps not counted (15, 10, 10 accepted
    # ones, polish too): 0.38 / 0.35, 0.39 / 0.50, 0.64 / 0.72, 0.37 / 0.87 (no equilibrium at ug
    # 0.2), 0.58 / 1.56, 86-96 s; (30, 10, 10) with refine_stage_tolerance 1e-4: 0.39 / 0.82,
    # 0.55 / 0.53, 87 s (the times in this comment are before stops 32 and 33 made the Gauss-Newton
    # pass faster: the same models, recordings 0-4 in 52-61 s, median 53.8 s, instead of 89-130 s;
    # `--set refine_growing_evaluations=15,10,10` gives the old models in about two thirds of the time)
    refine_growing_evaluations: tuple = (30, 20, 20)
    # on low-SNR records (low_snr_below_db) the refinement runs a second pass in these growing windows (every
    # start and try as in the first pass, which keeps refine_growing_windows), its candidates renamed with
    # estimators.LOW_SNR_SUFFIX, and both passes' candidates compete; empty: one pass. Why (stop 95,
    # bench/oracle_bench.py --snr 30 --seeds 296,297 --stages 5:20,10:20,25:20,50:20,400:5): with the
    # plant's own support, from equation error, windows of 10 lose an LCL resonance at 30 dB (296: cost
    # 5137 at windows of 10, W 2220 at ug 0.8, where the truth's basin has 2837) and single shooting never
    # finds it again; a first stage of 5 leads into the truth's basin (single shooting's cost 110.2 on 296
    # and 110.6 on 297, as from the true coefficients; 0.317 / 0.510 % and 0.234 / 0.372 %). In the engine
    # (support ~230 terms) the 5,10,25,50 schedule alone, in place of the default
    # (`bench/candidates.py --seed S --noise 30 --set refine_growing_windows=5,10,25,50 --set
    # refine_growing_evaluations=20,30,20,20`, 296-303) was better on 296 (9.772 / 25.68 % -> 1.264 /
    # 1.647 %), 297 (1.548 / 25.39 -> 1.254 / 6.171 %), 300 (1.280 / 0.551 -> 0.644 / 0.839 %) and 302 (OOD
    # 4.631 -> 0.764 %, but spurious at ug 0.2-0.6) and worse on 298, 299 (1.684 / 7.681 -> 7.008 / 10.22 %,
    # spurious everywhere), 301 and 303 (1.192 / 1.736 -> 1.663 / 4.108 %); the first family itself
    # diverged on 297-299 (rest growth rates up to 160 1/s: windows of 5 samples do not see a slow
    # instability). Both passes (`bench/sweeps/snr30-two-passes-s95.json`): the selection took the better
    # pass's model on 7 of 8 (302 kept the first pass's 0.637 / 4.631 % against 0.552 / 0.764 % spurious),
    # OOD median 3.32 -> 1.88 %; on 184-191 two choices changed, 187 1.291 / 8.945 -> 3.232 / 1.971 %, 191
    # 1.227 / 4.587 -> 1.007 / 1.257 % (OOD median 5.51 -> 2.18 %); 30 dB fits ~2x longer. Until stop 94
    # this setting replaced the default windows on low-SNR records
    # (off): 20,50,100 that way on 296-303 (stop 94, `snr30-lowsnr-windows-296-303-s94`) were better on
    # 296-298 and 303 and worse on 299-302 (299 1.684 / 7.681 -> 2.562 / 49.35 %, 302 W 12 -> 1495); from
    # windows of 20 the first family keeps both resonances more often (stop 85, 185 and 187)
    # Stop 97, 20,50,100 (30, 20, 20 evaluations) as the second pass in place of 5,10,25,50 (`bench/candidates.py
    # --seed S --noise 30 --set refine_growing_windows_low_snr=20,50,100 --set
    # refine_growing_evaluations_low_snr=30,20,20`, 296-303, against snr30-two-passes-s95 and the default's
    # tables of 297-301 on the same machine, which gave its rows but 299's, 1.671 / 8.812 % against 1.684 /
    # 7.681): better on 297 (1.254 / 6.171 ->
    # 0.878 / 4.769 %) and 303 (1.192 / 1.736 -> 0.674 / 1.257 %), worse on 296 (1.264 / 1.647 -> 3.646 /
    # 9.171 %, spurious) and 300 (0.644 / 0.839 -> 0.791 / 1.746 %), 298 mixed (1.432 / 2.018 -> 0.781 / 2.970
    # %), 299, 301, 302 the same. Both as passes two and three (the tables of 297-301 merged and replayed):
    # only 297 and 298 change, as above. A reshuffle for half again the fit time: not taken
    refine_growing_windows_low_snr: tuple = (5, 10, 25, 50)
    # evaluations per stage of refine_growing_windows_low_snr (empty: refine_growing_evaluations, which
    # must then have as many stages)
    refine_growing_evaluations_low_snr: tuple = (20, 30, 20, 20)
    # the training records count as low-SNR (refine_growing_windows_low_snr, selection_window_excess) where
    # their estimated signal-to-noise ratio (noise.estimated_snr_db: per state RMS / noise std, the median
    # over the states) is below this (dB); 0: never, inf: any noisy records. Measured (stop 96, 8 recordings
    # of the protocol and of each scenario of bench/scenarios_bench.py but "inputs 20 dB quieter"):
    # 39.8-40.1 dB at 40 dB, 34.9-35.1 at 35, 29.8-30.2 at 30. Until stop 95 a noise floor (noise.noise_floor_error,
    # low_snr_noise_floor 3.5 %) decided; it weighs each record by its own norm: records starting at ug
    # 0.6-1.0 reach 2.5 % at 40 dB, above the protocol's 2.1 % at 35 dB, so no floor tells 35 dB from 40,
    # and 35 dB ran one pass. At 35 dB, unseen 304-319 (bench/sweeps/snr35-*-s96.json, candidate tables;
    # one pass replayed with bench/selection_replay.py --first-pass-only --no-window-check): IOD median
    # 0.846 -> 0.587 %, worst 4.241 -> 1.400 %; OOD median 1.495 -> 1.135 %, worst 6.303 -> 2.684 %; W at
    # ug 0.8 worst 186 -> 20; better on 6 (304 2.681 / 6.303 -> 0.611 / 0.766 %, 306 4.241 / 1.643 -> 0.289 /
    # 0.602 %), worse on 4 (313 0.248 / 1.538 -> 0.401 / 2.659 %, 315 0.435 / 0.868 -> 0.239 / 1.270 %, 311,
    # 305), 6 the same; within both 40 dB targets with no spurious mode 1 of 16 either way; spurious modes
    # on 5 of 16 against 3. The short-window check alone changed 304 only. Fits median 80 s, 62-249 s
    # (304 in one pass: 30 s)
    low_snr_below_db: float = 37.5
    # at most this many windows per growing-window stage, evenly spread over the records (0 or an
    # empty list: all of them); a stage's Gauss-Newton pass is linear in its windows. Stop 67 (to buy
    # fit time), 240 of the 480 windows of 10 (`bench/setting_sweep.py run --name maxwin240-s67 --set
    # refine_growing_max_windows=240,0,0 --seeds 0-12`): 7 of 13 within both accuracy targets with no
    # spurious mode against 9 (lost 0, 5, 7, 9; won 1, 3), recording 7 at 2.72 / 2.91 %; compression
    # 12 of 13 against 9. Fits median 50.3 s, but the machine had sped up meanwhile (recording 1 with
    # the default: 76.9 s an hour before, 56.5 s just after), so the saving is not measured. Not taken
    refine_growing_max_windows: tuple = ()
    # RK4 steps per sample in the growing-window stages (the polish uses 2), either raised to keep
    # refine_max_step (so 1 needs refine_max_step 0 at 10 kHz since stop 38). Measured at 1 (40 dB,
    # recordings 0 / 1 / 2): 53 / 48 / 48 s instead of ~70 s, but recording 0's pruned model was
    # lost and an unstable refined one chosen (1.02 / 1.62 %), 1 and 2 0.24 / 1.17 %, 0.37 / 2.04 %
    refine_growing_substeps: int = 2
    # on clean data: where the model the selection would take after the one-stage refinement does not
    # reproduce the training and small-signal records run freely within this error (%), the merged
    # model is refined in growing windows and pruned too (as on noisy data), and that family competes
    # (needs refine_growing_windows; inf: off). Clean data within the clean targets score
    # ~0.004-0.03 % (protocol, 10 and 20 kHz); at 5 kHz the sparse re-fits miss true terms (equation
    # error on 3 samples per LCL period) and the chosen candidate scored 0.38 %. Stop 61 (0.1 -> 0.05):
    # with filter_terms "physics" the 5 kHz clean recording 1's one-stage refinement scored 0.082 %,
    # under 0.1, and its model missed the clean targets (0.168 / 0.318 % IOD / OOD); with 0.05 the
    # growing-window family wins, 0.0031 / 0.028 % (87 coefficients, 40 s). Every other clean fit of
    # make bench, bench-plants, bench-scenarios and bench-limits chose a candidate at 0.004-0.037 %
    clean_growing_error: float = 0.05
    # longest RK4 step (s) of the refinement: with coarser samples the substeps per sample rise to keep
    # it (at the protocol's 10 kHz the two substeps give 5e-5 s already); 0: the substeps as set.
    # Measured (stop 38, 5 kHz, where it gives four): clean records with clean_growing_error, seeds
    # 0 / 1, 0.003 / 0.023 and 0.003 / 0.022 % IOD / OOD (two substeps there: 0.314 / 0.417 % on
    # seed 1). 40 dB, seeds 0-3: 0.624 / 0.397, 4.95 / 8.29 (W 1630), 1.02 / 0.566, 0.437 / 0.378 %
    # (seeds 0 / 1 with two substeps: 1.22 / 7.38, 0.543 / 1.01); with two substeps kept in the
    # growing-window stages only: 1.11 / 7.24, 0.305 / 0.749, 0.996 / 1.27, 1.24 / 0.467 %. At 40 dB
    # 5 kHz is a lottery either way (half the protocol's samples, three per LCL period)
    refine_max_step: float = 5e-5
    # between the growing-window stages, the terms whose removal the last stage's quadratic cost
    # model says raises its cost by at most this fraction are dropped (backward elimination, as the
    # prune budgets); 0: every stage keeps the start's support
    refine_stage_prune_budget: float = 0.0
    # the two refinement starts on noisy data (the best merged / re-fitted model, the noise-compensated
    # backbone): "both" refines them side by side (a thread each); "auto" (the default) is "both"
    # where torch has two threads or more and "fallback" on one (there both would run one after the
    # other, the second start's whole refinement added: the live identifier trains on one thread,
    # leaving a core for the link, and its final model takes 82.5 s of issue 4's 90 s already);
    # "fallback" refines the first on
    # every thread (the shooting windows shared out) and the second only where the selection over
    # the first's family does not take one of its models, or takes one inconsistent with a point
    # where the records sat at rest. Measured (stop 22, 40 dB, 2 cores, benchmark recordings 0-4):
    # the same explicit models as "both" (the first start's family won all five), 50-60 s instead
    # of 85-91 s; on the demo recording the first family fails and both run (as with "both").
    # Re-measured (stop 63, 40 dB protocol recordings 0-23, `bench/setting_sweep.py`, files
    # bench/sweeps/default-s62-alternatives.json and both-s63.json): the fallback's models are no
    # longer the same. "both": within both accuracy targets with no spurious mode on 17 of 24
    # against 15 (the tuned 0-9: 6 against 5; the unseen 10-23: 11 against 10), no operating point
    # wrong (1 before), and the second family's models are the fit's alternatives too: of the 240
    # microgrid / weak-line verdicts 29 wrong against 31, 25 of them flagged open against 19 (right
    # ones flagged: 18 against 11 of about 210). Fit median 56.5 s against 38.5 s (2 cores).
    # Stop 69: "fallback" again, with the first start's long-window branch (refine_long_branch) and
    # selection_rest_offset 0.1: 17 of 24 as "auto", none spurious (2), fits median 43.5 s against
    # 59.0 (bench/sweeps/longbranch-restoffset-s69.json; see refine_long_branch). Since stop 73
    # "fallback" also runs the second start where the first start's refinement is lost (neither
    # unpruned refined model beats holding the records' first states, selection._unpruned_refinement_lost):
    # the plants' vendor-c recording 1 at 40 dB from 1.21 / 3.75 % (the first family's round 2,
    # consistent at 1.32x the floor, W 1433: an LCL resonance lost) to 0.428 / 0.895 % (71
    # coefficients, W 17), fit 75 s against 50 s (`bench/candidates.py --plant vendor-c --seed 1 --noise 40`);
    # vendor-c recording 0 (lost too, but its second start ran already) the same model. No protocol
    # recording 0-23 has such a first refinement (their refined models score 1.9-16 % against holds of ~40 %)
    refine_starts: str = "fallback"
    # where both starts run side by side: the second (the noise-compensated backbone, known right
    # after the backbone) starts beside the hybrid's training instead of after the distillation; the
    # hybrid, distillation and re-fits then run on one torch thread (on two, their OpenMP team
    # spin-waits while the start holds a core: the hybrid took 22.6 s instead of 7.2 s) and the limit
    # search follows the start on its thread. Stop 68 (to buy fit time), 40 dB protocol recordings
    # 0-12 (`bench/setting_sweep.py run --set refine_second_start_early=true`, bench/sweeps/early-s68.json,
    # against late-s68.json, the default, measured 18 minutes before): the same verdicts and counts, 7 of 13 models the
    # same to the bit, the others within ~1e-7 relative (the hybrid on one thread rounds otherwise);
    # CPU median 94.9 s against 99.4 s, but no wall time saved: median 56.5 s both, per recording -1.0 s
    # median, 8 of 13 quicker, -4.1 to +21.8 s (recording 3; the same models took 127 s in an earlier
    # run). The first start, which needs the distillation, stays the longest path, and the threads
    # contend for the GIL beside the hybrid. Off, so the models stay as they were
    refine_second_start_early: bool = False
    # a stage of the noisy-data refinement (growing windows, polish) ends early when an accepted step
    # lowers its cost by at most this fraction. Stop 66 (to buy fit time): the windows-of-50 stage's
    # last 5-10 of its 20 evaluations lower its cost by under 1e-6 each (recordings 1, 4, 9 at 40 dB),
    # but with 1e-6 (`bench/setting_sweep.py run --name tol6-s66 --set refine_stage_tolerance=1e-6`,
    # stopped after recordings 0-12, bench/sweeps/tol6-s66.json) 6 of 13 were within both accuracy
    # targets with no spurious mode against 9 (lost 0, 4 and 9, none won), fits median 55.0 s against 64.9 s
    # (stop 65's run, another machine; here recording 1 took 54.7-61.9 s with 1e-8 in eight runs)
    refine_stage_tolerance: float = 1e-8
    # the first this many growing-window stages carry their coefficient tangents in float32
    # (TrajectoryFitter.single_precision: the states, every cost compared, the later stages, the
    # polish and every Hessian that prunes stay float64); 0: float64 throughout. Stop 67 (to buy fit
    # time): float32 makes the tangents' products 3-4x quicker and a Gauss-Newton pass ~25 % (0.48 ->
    # 0.36 s, windows of 10, one thread), but its steps stall above float64's floor (clean records,
    # 5 evaluations: replay error 4.5e-4 against 7e-9) and the models move. 40 dB protocol
    # recordings 0-9 (`bench/setting_sweep.py run --set refine_single_precision_stages=N`): 3 (all
    # three stages, bench/sweeps/single3-s67.json) within both accuracy targets with no spurious mode
    # against 6 (lost 0, 5, 7), fits median 56.3 s; 2 (windows 10 and 25, single2-s67.json) 5 of 10
    # (lost 4 and 7, won 6), median 68.8 s, no quicker than float64 on the same machine (recording 1:
    # 74-80 s; with 3, 61.8 s). Not taken
    refine_single_precision_stages: int = 0
    # on noisy data: prune-and-polish rounds. Each round prunes the last round's polished model at the
    # first prune budget, then re-fits it (round 1 with every polish stage, later rounds with the
    # last one); round R's candidate is "pruned +B % xR". Round 1 prunes at the refined model, whose
    # quadratic cost model is far off (predicted +0.1 %, the cost went 655 -> 20167 before the polish);
    # a later round prunes at a polished minimum, where it holds (recording 0: 352.7 -> 354.7 after
    # the polish). Measured (stop 23, 40 dB, benchmark recordings 0-4, IOD / OOD %, coefficients):
    # 1 round: 0.40 / 0.72 (135), 0.40 / 0.75 (129), 0.51 / 2.12 (147), 1.13 / 1.72 (170),
    # 0.32 / 1.95 (164); 3 rounds, every polish stage each: 0.29 / 0.40 (80), 0.59 / 0.58 (81),
    # 0.40 / 0.32 (94), 0.63 / 0.75 (118), 0.32 / 1.95 (164; the later rounds scored worse and were
    # not chosen), 66-80 s; 3 rounds, later ones with the last stage (the default): 0.28 / 0.44 (81),
    # 0.68 / 0.58 (81), 0.65 / 0.41 (102), 0.57 / 0.32 (117), 0.32 / 1.95 (164); 2 rounds: 0.29 / 0.77
    # (99), 0.58 / 0.61 (91), 0.40 / 0.69 (117), 1.20 / 1.07 (131); 4 rounds: 0.20 / 0.46 (72),
    # 0.81 / 0.78 (73), 0.61 / 0.39 (84), 0.52 / 0.87 (107). Fewer growing-stage evaluations (12, 8, 8)
    # to pay for it: 1.14 / 2.82, 1.24 / 5.21, 0.92 / 0.76. Later rounds at windows of 50 (8
    # evaluations) instead of 100: 0.26 / 0.28, 0.76 / 0.55, 0.58 / 0.38, 0.72 / 0.99, 0.58 / 1.87;
    # later rounds at +0.05 % (4 rounds): 0.25 / 0.34, 0.62 / 0.67, 0.68 / 0.54, 0.88 / 0.74; at
    # +0.2 % (2 rounds): 0.43 / 0.35, 0.91 / 0.46, 0.62 / 0.45, 0.87 / 0.71. Stop 40 (scratch, as
    # bench/candidates.py --set refine_prune_rounds=4, stop 39's engine, recordings 0-4), 4 rounds: the fourth round's model chosen on
    # 0, 1, 2 and 4, 0.15 / 0.47 (71), 0.91 / 0.44 (82, spurious unstable at ug 0.2), 0.53 / 0.49
    # (77, spurious at 0.2-0.4; it scored 1.9x the best and won only through the refined model's
    # inflated score, see selection_tolerance), 0.60 / 0.94 (127, spurious at 0.2-1.1); 3 unchanged;
    # 60-67 s. Not taken. Stop 80, 4 rounds with today's engine (`bench/setting_sweep.py run --name
    # prunerounds4-s80 --set refine_prune_rounds=4 --seeds 56-71 --noise 40`, against
    # default-unseen-56-71-s79.json): the fourth round chosen on 12 of 16, and the same 9 of 16 within both
    # accuracy targets with no spurious mode (none won, none lost), every target on 8 as before;
    # coefficients median 61 against 66, IOD median 0.325 against 0.369 %, OOD median 0.390 against
    # 0.451 %; fits median 44 s against 41 s. Stop 81 on the next two sets (prunerounds4-72-87-s81.json
    # against default-unseen-72-87-s79.json, prunerounds4-88-103-s81.json against
    # default-unseen-88-103-s80.json): 72-87 13 of 16 against 12 (won 83, 0.586 / 0.238 -> 0.121 / 0.505 %;
    # 84 took a sparser model with spurious modes at ug 0.2-0.6, outside the targets either way), 88-103
    # 6 against 7 (lost 103, 0.289 -> 0.545 % IOD; 98 0.703 / 1.282 -> 0.168 / 0.322 % but spurious at
    # ug 0.2). Over the 48: 28 against 28, spurious on 6 against 4, at most 84 coefficients on 41
    # against 39, fits median 50 s (72-87 and 88-103, this stop's machine; the defaults' 36 and 44 s
    # were measured at stops 79-80; the defaults on 104-119 this stop: 48.2 s). It reshuffles too, and
    # gains nothing on the targets: not taken
    refine_prune_rounds: int = 3
    # the rounds' budget is a fraction of the polished cost for this many training samples (the
    # protocol's 12 records of 401): with N samples it is scaled by this / N; 0: not scaled. The
    # cost grows with the samples, the rise that dropping a term the data support brings does not
    # grow with them in proportion: a fixed fraction pruned more of the true terms the longer the
    # records. Measured (stop 25, 40 dB, IOD / OOD %, coefficients): records of 80 ms, benchmark
    # recordings 0 / 1 / 2, unscaled 1.09 / 0.70 (64), 0.69 / 0.74 (64), 0.51 / 0.90 (91); scaled
    # (+0.05 %) 0.51 / 0.28 (62), 0.07 / 0.30 (74), 0.35 / 0.75 (96); recording 0 at +0.025 %:
    # 0.43 / 0.29 (86). 6 records of 40 ms (recording 0): unscaled 0.91 / 0.67 (122), scaled
    # (+0.2 %) 0.70 / 0.82 (92). The protocol's size: unchanged
    refine_prune_reference_samples: int = 4812
    # the order in which the rounds' pruning drops terms: a term of degree k (library.term_degrees)
    # ranks as if its removal cost this factor^-(k-1) of what it does, so a product goes ahead of a
    # plain signal that costs as little to lose; the budget counts the true cost. 1: cost alone.
    # Why tried: at 40 dB the rounds kept Pf*il_d and Pf*ig_d (+-540) in the grid-current rows and
    # dropped il_d (true 377): at the records' Pf the products stand in for it. Measured (stop 24,
    # scratch /tmp/exp/run.py, 40 dB, benchmark recordings 0-6 and the demo's, IOD / OOD %; "s":
    # a spurious unstable mode at ug 0.2-1.1; "ok": both 40 dB targets and none spurious):
    # 1 (default): 0.28 / 0.44 ok, 0.68 / 0.58, 0.65 / 0.41, 0.57 / 0.32, 0.32 / 1.95, 0.99 / 0.59,
    # 0.81 / 0.37, demo 0.95 / 2.90 (1 of 8 ok, none spurious); 10: 0.20 / 0.92 ok, 0.25 / 0.47 ok,
    # 0.40 / 0.40 ok, 0.79 / 0.89 s, 0.64 / 3.84 s, 0.39 / 0.23 ok, 0.68 / 0.44, demo 1.45 / inf
    # (4 of 8, but the demo's model blows up in the sag); 30 on 0-4: 0.19 / 0.62, 0.22 / 0.40,
    # 0.55 / 0.39, 0.65 / 0.85, 0.26 / 3.17; 5 with functions (cos, sin, a denominator) counting
    # as degree 2: 0.33 / 0.33 ok, 0.77 / 0.50, 0.82 / 1.20, 0.61 / 0.56, 0.48 / 2.09, 0.72 / 0.29 s,
    # 0.23 / 0.52 s, demo 0.23 / 0.55 ok; the same at 10: demo inf / inf, recording 0 1.74 / 0.79.
    # With filter_terms "physics": 10: 0.40 / 0.50 s, 0.62 / 0.42, 0.57 / 0.20, 0.42 / 0.38 ok,
    # 0.12 / 0.21 ok, demo 1.72 / 0.79 s; 5: 0.27 / 0.41 ok, 0.89 / 0.69, 0.26 / 0.50 ok,
    # 0.79 / 0.47, 0.26 / 0.69 ok, 0.58 / 0.47, but recording 6 diverged in both refinements
    # (the backbone chosen: 5.0 / 5.4 %, 269 s) and the demo 1.94 / 0.76 s. Each setting moves
    # single recordings by +-0.3 % either way; none is safe enough to be the default
    refine_prune_degree_preference: float = 1.0
    # the prune rounds do not drop a coefficient whose removal (on their quadratic cost model) would
    # leave the model's Jacobian a mode of modulus below this (1/s) at every rest state of the records
    # where it had none (trajfit.backward_elimination); 0: off. Such a mode is a state the model no
    # longer pulls back (selection.ZERO_MODE_MODULUS counts its equilibrium as none), which the
    # windows' cost barely sees: stop 75's protocol recording 4 at 40 dB, rounds 2 and 3 (84 and 73
    # coefficients, 0.226 / 0.303 and 0.231 / 0.290 % IOD / OOD) had lost the pull on Qf (a mode at
    # 1e-5 1/s) and were inconsistent with every rest point, so round 1 (104) was chosen. Measured
    # (stop 76, bench/candidates.py --set refine_prune_zero_mode=0.01 on the 24 protocol recordings
    # at 40 dB, against stop 75's tables replayed): the candidates of 21 fits the same to the last
    # digit; recording 4 now takes round 3, 74 coefficients, 0.232 / 0.448 % (was round 1, 104,
    # 0.194 / 0.301 %); recordings 3 and 18 other candidates but the same choice: 21 of 24 within
    # both 40 dB targets as before, 20 of 24 at most 84 coefficients (19). Asked at any one rest
    # point instead of all, it changed 6 of the first 9 fits and put recordings 3, 7 and 8 outside
    # the targets (a slow mode crossing zero as terms go is no lost pull). The selection's own
    # threshold (selection.ZERO_MODE_MODULUS)
    refine_prune_zero_mode: float = 0.01
    # on noisy data, the refinement's products of the frequency state (roles.frequency) written about
    # its rest value P0, (Pf - P0)*s instead of Pf*s (estimators._couplings_centred): the same field
    # at the start, but Pf*s ≈ P0*s at every rest point, and the refinement and its pruning could
    # trade s for the product (at 40 dB they kept Pf*il_d, Pf*ig_d at +-540 in the grid-current rows
    # and dropped il_d, true 377). Measured (stop 26, scratch /tmp/exp/run.py, 40 dB, benchmark
    # recordings 0-8 and the demo's, IOD / OOD %; "ok": both 40 dB targets): off: 0.28 / 0.44 ok,
    # 0.68 / 0.58, 0.65 / 0.41, 0.57 / 0.32, 0.32 / 1.95, 0.99 / 0.59, 0.81 / 0.37, 0.38 / 0.75 ok,
    # 0.30 / 1.00, demo 0.70 / 2.97 (2 of 10 ok, median 0.61 / 0.59); on: 1.09 / 4.17 (spurious
    # unstable at ug 0.2), 0.42 / 0.81 ok, 0.19 / 0.79 ok, 0.17 / 0.76 ok, 0.66 / 3.66 (W 735),
    # 0.44 / 0.65 ok, 0.90 / 1.25, 0.34 / 0.76 ok, 0.35 / 0.81 ok, demo 0.82 / 0.54 (6 of 10 ok,
    # median 0.43 / 0.80; worse tails). Centred only from the first prune round's polish on (the
    # growing stages in the plain products): 0.24 / 0.46 ok, 0.50 / 0.73, 0.77 / 0.33, 0.94 / 0.60
    # (spurious 0.2-0.6), 0.41 / 0.91 ok, 0.62 / 0.73 (spurious 0.2-0.6), 0.97 / 0.83 on 0-6.
    # `make bench` with it on: bench/RESULTS_centred.md (20 dB spurious modes at every ug, 30 dB OOD
    # 15 %). `make demo` with it on (one thread): 0.48 / 0.35 %, but no equilibrium at ug 0.4 and 0.8
    # (where the small-signal records sat at rest) and a boundary at 1.0008 (plant 1.166). Not the
    # default: more recordings within the accuracy targets, but 4 of 10 with a stability analysis
    # gone wrong inside ug 0.2-1.1 (a spurious mode, no equilibrium, W 735) against none
    refine_centred_couplings: bool = False
    # the prune rounds' re-fits (window lengths, evaluations per stage; a later round the last stage
    # only). Stop 69 (round 1 prunes at a point that is not a minimum, see refine_prune_rounds: prune
    # it at a minimum of the longer windows instead), growing windows 10, 25, 50, 100 (30, 20, 20, 8
    # evaluations) and polish windows of 100 only (6), `bench/setting_sweep.py run --name w100-s69`,
    # recordings 0-12 at 40 dB, against late-s68.json: recordings 2 and 6 from 1.67 / 2.06 and
    # 0.73 / 1.41 % to 0.43 / 0.47 and 0.22 / 0.27 % (every target; bench/candidates.py showed the
    # sparse models of recording 2 at 1.3-1.9 % IOD before), IOD worst 0.59 % against 1.67, but
    # 4, 5 and 7 lost (4: 2.43 % OOD and its operating point 3 p.u. off in Q; 7: spurious at ug 0.2
    # and the rescue, 130 s) and 1 spurious at ug 0.2-0.4: 8 of 13 within both accuracy targets with
    # no spurious mode against 9, every target 6 against 8, fits median 58.5 s against 56.5. The
    # schedule reshuffles which recordings pass rather than adding any. Not taken. Also measured at
    # stop 69 (scratch code, bench/candidates.py, recording 2): (a) round 1's elimination started at
    # its quadratic cost model's minimum (one Gauss-Newton step with the profiled gradient from where
    # the windows-of-50 stage stopped): 1.668 / 2.060 % against 1.673 / 2.061, the step is tiny, so
    # the refined model is at that minimum and the quadratic model's error is its curvature's, not a
    # gradient left over; (b) both schedules from one start (the windows-of-100 stage and its prune
    # rounds as a branch after the growing stages, refine_starts "fallback": 47.5 s): the branch's
    # 0.427 / 0.474 % round scored 2.41 % against the default rounds' 3.17 %, but the selection takes
    # the family of the best-scoring candidate (the default family's unpruned model, 2.20 %) and
    # chose 1.673 / 2.061 % again; choosing the family by its pruned models' scores was measured
    # worse before. Stop 78, polish windows (50, 200) (the long branch then at 200 too;
    # `bench/setting_sweep.py run --name polish200-s78 --set refine_polish_windows=50,200 --seeds
    # 40-55`, against default-unseen-40-55-s78.json): 9 of 16 within both accuracy targets with no
    # spurious mode against 10 (won 40, 44, 54; lost 42, 43, 50, 51), at most 84 coefficients 12
    # against 15: a reshuffle again. Not taken
    # Stop 97, at 30 dB (both passes' polish and long branch at 200 samples, 2 windows a record;
    # `bench/candidates.py --seed S --noise 30 --set refine_polish_windows=50,200`, 296-301, against the
    # default's tables on the same machine, 296's from snr30-two-passes-s95): better on 296 only (1.264 /
    # 1.647 -> 1.021 / 0.779 %), worse on 297 (0.935 / 7.823 % against 1.254 / 6.171, spurious), 298 (1.432 /
    # 2.018 -> 1.939 / 1.318 %, spurious), 300 (0.644 / 0.839 -> 1.397 / 2.854 %) and 301 (0.873 / 0.913 ->
    # 2.970 / 5.858 %), 299 about the same (1.671 / 8.812 -> 1.477 / 9.004 %), though with the
    # plant's own support single shooting keeps gaining at 30 dB (`bench/oracle_bench.py --snr 30 --seeds
    # 296,297 --stages 5:20,10:20,25:20,50:20,100:8,200:5,400:5`: windows of 100 / 200 / 400 0.645 / 0.438,
    # 0.380 / 0.748, 0.254 / 0.538 % on 296; bench/ORACLE_RESULTS_snr30_long_windows.md). 100,400 on 296: 2.124 /
    # 1.097 %. Not taken
    refine_polish_windows: tuple = (50, 100)
    # on noisy data: a second branch of each refinement start after its growing-window stages, the
    # refined model re-fitted in the polish's longest windows (this many evaluations), then pruned and
    # polished there for refine_prune_rounds rounds; its candidates ("refined at long windows",
    # "pruned +B % xR at long windows") compete in the selection as a family of their own (the
    # schedule of w100-s69 above, beside the default one at the cost of the branch alone). Measured
    # (stop 69) with refine_starts "fallback", so that the first start runs alone on both threads
    # and the second only where the first's families give no model consistent with the rest points:
    # `bench/setting_sweep.py run --name longbranch-fallback-s69 --set refine_starts=fallback --set
    # refine_long_branch=true` on 40 dB protocol recordings 0-12 (and `... -13-23` on 13-23), against
    # the default (late-s68.json, default-s65.json on 13-23, the same models): within both accuracy
    # targets with no spurious mode 17 of 24 either way (won 6, 16, 20; lost 7, 13, 17);
    # every target 15 of 24 either way; spurious unstable modes on none against 2 (seeds 20, 22); fits
    # median 42.5 s against 56.5 on 0-12 (47.1 against 61.3 on 13-23), worst 56.7 s against 127 s (no
    # second start, no rescue), CPU median 66.6 s against 99.4. But the operating point is off by more
    # than 0.3 p.u. in Q on 3 of 24 (3: 3.52, 17: 0.89, 22: 0.66 p.u.) against none, and of the 240
    # microgrid / weak-line verdicts 32 are wrong against 29 (25 of them flagged by the alternatives
    # against 25). The branch's rounds score better than the default family's where they are worse
    # models too (7: 3.25-3.49 % against 4.3-4.4 %, which made the rescue run and win there).
    # Recording 3's chosen model has its equilibrium 1.94 (relative) from a rest state where a record
    # sat still (bench/candidates.py; the chosen models of 2 and 6 within 0.04): with
    # selection_rest_offset 0.1 such models count as inconsistent, and none of the three operating
    # points stays off (3: 0.023, 17: 0.020, 22: 0.14 p.u.; the rescue ran on 3 and 22). All three
    # together, the default since stop 69 (`bench/setting_sweep.py run --name longbranch-restoffset-s69
    # --set refine_starts=fallback --set refine_long_branch=true --set selection_rest_offset=0.1 --seeds
    # 0-23`, against late-s68.json + default-s65.json): 17 of 24 within both accuracy targets with no
    # spurious mode either way (won 6, 16, 20; lost 7, 13, 17), every target 14 against 15 (one more
    # over 84 coefficients), spurious modes on none against 2, operating point off on none either way;
    # microgrid / weak-line verdicts 29 of 240 wrong either way, 21 of them flagged by the alternatives
    # against 25, and no right one flagged against 18 (4 false alarms against none); fits median
    # 43.5 s against 59.0 s, worst 97 s against 127 s, CPU median 68.3 s against 99.4 s
    refine_long_branch: bool = True
    refine_long_branch_evaluations: int = 8
    # Stop 80, twice the evaluations (`bench/setting_sweep.py run --name polisheval-s80 --set
    # refine_polish_evaluations=16,12 --set refine_long_branch_evaluations=16 --seeds 56-71 --noise 40`,
    # against default-unseen-56-71-s79.json): 5 of 16 within both accuracy targets with no spurious mode
    # against 9 (won 57; lost 56, 58, 61, 64, 70), microgrid and weak-grid verdicts 19 of 160 wrong,
    # fits median 53 s against 41 s. Longer polishes do not mend the fits that no candidate gets right.
    # Half (`--name polisheval-half-s80 --set refine_polish_evaluations=4,3 --set
    # refine_long_branch_evaluations=4`, same recordings): 7 of 16 (won 63; lost 58, 64, 70), at most 84
    # coefficients on 8 against 12, verdicts 29 of 160 wrong, fits median 43 s
    refine_polish_evaluations: tuple = (8, 6)
    # Levenberg-Marquardt damping (relative to the normal equations' diagonal) that each polish stage
    # starts from (the growing stages start from 1e-5). Stop 66: at 1e-5 a polish after pruning
    # often spends its first 4 of 6 evaluations on rejected trial steps (the damping doubling up to
    # ~1e-2) and takes 0-2 steps (recordings 1, 4, 9 at 40 dB, `bench/fit_time.py`). Measured at 1e-2
    # (`bench/setting_sweep.py run --name polishdamp-s66 --set refine_polish_damping=0.01`, recordings
    # 0-23, bench/sweeps/polishdamp-s66.json, against default-s65.json): within both accuracy targets
    # with no spurious mode 10 of 24 against 17 (lost 5, 7, 9, 12, 14, 17, 19, 21, 23; won 1, 16),
    # operating point off by more than 0.3 p.u. in Q on 3 (7, 12, 17) against none, microgrid /
    # weak-line verdicts 46 of 240 wrong against 29 and none of them flagged by the alternatives.
    # The short polishes' rejected trials are part of what makes these models: not taken
    refine_polish_damping: float = 1e-5
    # the controller integrators' equations in the refinement: "linear" keeps them to the constant
    # and the plain signals (:func:`~.library.integrator_row_mask`); "error" to those without their
    # own loop's integrators (an integrator integrates an error its own state does not enter;
    # roles.integrator_loops; measured worse, stop 62: microgrid or weak-grid verdict wrong on 4 of the
    # 40 dB recordings 0-5 against 3, within both accuracy targets 1 against 2); "cascade" also keeps
    # each loop's integrators out of the rows of the loops outside it (the voltage loop's rows lose
    # gamma: roles.integrators lists the loops from the outer one in); "any" lets them take every term
    # of the library. Stop 98, unseen 40 dB protocol recordings (bench/candidates.py --set
    # integrator_terms=..., then bench/setting_sweep.py import; within both accuracy targets with no
    # spurious mode, against the defaults' default-unseen-*-s97 / -s98 rows): "error" on 320-383
    # (integrator-error-unseen-320-383-s98) 35 of 64 against 36 (37 with stop 98's start rule on 357),
    # spurious 13 against 14, <= 84 coefficients 58 against 51, a wrong 3-bus or weak-line verdict
    # (bench/microgrid_bench.quick_verdicts, the chosen model alone) on 12 recordings against 11; 10 of 16
    # on 368-383 but 9 against 13 on 320-335. "cascade" (integrator-cascade-unseen-320-383-s98):
    # 42 of 64 against 36 (11, 10, 10, 11 of the four 16s against 13, 8, 8, 8), spurious 13 against 14,
    # <= 84 coefficients 57 against 51, a wrong verdict on 13 recordings against 11; on 384-391 7 of 8
    # against 6, a wrong verdict on 1 against 2: per recording, better on 19 of 320-391, worse on 13.
    # Stop 99, make bench with it (bench/results_cascade.json, against the defaults' run on the same
    # machine): the ten 40 dB recordings 5 of 10 within both accuracy targets with no spurious mode
    # against 10 (spurious at ug 0.2-0.6 on recordings 0, 4 and 8; IOD 0.577 and 0.931 % on 2 and 5),
    # the saturation plant at 40 dB 1.04 / 8.48 % against 0.316 / 3.12 %, 30 dB 0.747 / 1.28 % against
    # 0.405 / 0.441 %. Over the 82 standard-plant recordings better on 19, worse on 18: not taken
    # Both reshuffle which recordings pass; the slow mode they move (the voltage loop's integrators,
    # spurious at ug 0.2-0.6) is pinned by 40 ms records to a few tenths of 1/s either way
    integrator_terms: str = "linear"
    # Stop 50, measured and dropped (scratch setting, bench/sweeps/angle-relative.json): the angle only
    # inside the grid terms ug·cos/sin(theta_g - delta), without delta, sin(delta), cos(delta) in Θ and
    # Θ_ext (equations invariant to the grid's phase, as the plant's are): recordings 0-9 at 40 dB,
    # 4 within both targets with no spurious mode against 7, spurious modes at ug 0.2-0.6 on 2,
    # IOD / OOD median 0.48 / 0.81 against 0.41 / 0.55 %. At 40 dB the lone angle terms stand in for
    # part of what the grid terms and the slow states carry along the records; the microgrid instead
    # evaluates each unit in its bus voltage's frame (analysis.microgrid)
    # the output filter's equations (rows of the roles' voltage and current pairs) in the
    # refinement: "physics" keeps them to the constant, the dq signals, the grid terms and the
    # frame-frequency coupling with their own pair's other axis (:func:`~.library.filter_row_mask`),
    # the kept terms re-fitted at each refinement start to the start's own field over the records'
    # samples; "any" lets them take every term of the library. Why: with "any", controller states
    # and products stand in for the currents where the records are (40 dB, protocol seed 22: dvc_d/dt
    # took 2612 - 1.86e4*phi_d + 2.0e4*gamma_q - 7350*gamma_d - ..., none of which the plant has) and
    # move the model's equilibrium where the plant rests beyond the records (ug 0.2: ig_d 0.08 p.u.
    # against 0.74): spurious unstable modes at low ug on 4 of 24 recordings, and 90-175
    # coefficients. Measured (stop 47, bench/setting_sweep.py, 40 dB protocol recordings 0-23,
    # bench/sweeps/filter-physics-project.json against default-stop47-any.json): both accuracy
    # targets and no spurious mode 14 of 24 either way (benchmark recordings 0-9: 4 against 7; never
    # tuned on, 10-23: 10 against 7); spurious modes on 2 (seed 4 at ug 1.0-1.1, seed 22 at
    # 0.2-0.6) against 4; <= 84 coefficients on 21 against 2 (median 70 against 96); every 40 dB
    # target on one recording 14 against 2; IOD median 0.37 against 0.31 %, OOD 0.49 against 0.62 %,
    # worst 1.67 / 2.06 % (seed 2) against 0.60 / 1.31 %. But on the other inverters
    # (bench/PLANTS_RESULTS_filter_physics.md, 40 dB, recordings 0-2) both accuracy targets on 1 of 9
    # against 5: standard 0.615 / 0.166, 0.278 / 1.22, 1.67 / 2.06 %; vendor-b 0.506 / 0.587,
    # 0.284 / 0.382 ok, 0.581 / 1.01; vendor-c 2.77 / 3.29 % (both refinement starts lost: the
    # backbone chosen, 303 coefficients, spurious at every ug; "any" 0.356 / 0.272 %), 0.732 / 3.43,
    # 2.8 / 2.91 (as with "any"); an equilibrium at every grid point on 9 of 9 against 7. Then not the
    # default: sparser and better on the unseen protocol recordings, less robust off the protocol.
    # The re-fit of stops 21-46 (equation error on the records' derivatives, noise-compensated)
    # started recordings 6 and 7 at an unstable LCL mode (+2000 1/s; 5 of 11 within both targets
    # against 8 with "any", bench/sweeps/filter-physics.json); "physics" on the voltage pair only,
    # with the field re-fit: 10 of 24, spurious modes on 5, 13 compressed (filter-voltage-project.json).
    # Stop 48: where no restricted refinement runs freely through the records (or a noisy fit stays
    # above refine_retry_ratio x its noise floor) the starts are refined again with these rows free
    # (estimators.PISML._unrestricted_fallback): vendor-c seed 0 0.356 / 0.272 % as with "any"; on
    # the protocol it runs on seed 22 only (its "any" row, filter-physics-fallback.json). Measured
    # with it off the protocol: other inverters 2 of 9 within both 40 dB targets against 5
    # (bench/PLANTS_RESULTS_filter_physics.md), the scenarios' 40 dB rows 5 of 14 against 10, 11 of
    # 14 at <= 84 coefficients against 3 (bench/SCENARIOS_RESULTS_filter_physics.md). Not the default.
    # Stop 49, the filter rows kept only from the frequency products other than their own coupling and
    # the angle outside the grid terms (controller states, powers and products kept; scratch, not a
    # setting): recordings 0-5 none within both targets against 5 of 6, OOD median 1.66 against
    # 0.55 % (bench/sweeps/filter-frame.json): those products offset the controller states that stand
    # in for the currents, and without them the sag goes wrong; all or nothing.
    # Stop 60: every comparison above with "any" ahead was on data the settings were tuned on with
    # "any" (protocol recordings 0-9, the scenarios' and the other inverters' first seeds). On 40 dB
    # data no setting was tuned on, both accuracy targets with no spurious mode, "physics" against
    # "any": protocol recordings 10-23 10 of 14 against 7 (filter-physics-stop59.json,
    # default-stop59-selection.json); six off-protocol scenarios, seeds 2-3, 6 of 12 against 4
    # (bench/sweeps/scenario-*-{physics,any}.json); vendor-b / vendor-c seeds 3-4 3 of 4 against 2
    # (bench/PLANTS_RESULTS_seeds_3-4_*.md): 19 of 30 against 13. Made the default, it lost what those
    # counts do not see, the operating points: `make bench` (bench/RESULTS_filter_physics.md) gave
    # equilibria 1.5 and 2.6e3 p.u. off in Q over ug 0.8-1.1 on recordings 3 and 4 (any: <= 0.24), and
    # `make bench-microgrid` (bench/MICROGRID_RESULTS_filter_physics.md) a wrong verdict or operating
    # point on 3 of 10 (recording 2 unstable, +0.37 1/s; 3 and 4 Q 0.48 / 0.54 for 0.073, load-step
    # errors 72 / 82 %) against none; the demo's model (119 coefficients, 0.70 / 1.53 %) turned the
    # demo's microgrid unstable (+0.033 1/s; the plant -1.53). Back to "any". But on the unseen
    # recordings 10-23 (bench/sweeps/*-stop60-op.json) Q's equilibrium is > 0.3 p.u. off on 1 of 14
    # with "physics" and 3 of 14 with "any"; in the microgrid (recordings 10-15,
    # bench/MICROGRID_RESULTS_10-15_filter_physics.md against MICROGRID_RESULTS_10-15.md) "physics"
    # gives every verdict and boundary right, load-step errors 0.19-4.7 % against 0.37-12.2 %, and no
    # wrong grid-strength verdict against 2. Unseen, "physics" is ahead on everything measured.
    # Stop 61: recordings 3 and 4's far equilibria were models with a zero mode (6e-4 and 1e-5 1/s
    # at every rest point) that the selection took for consistent; it now counts such an equilibrium
    # as none (selection.ZERO_MODE_MODULUS). With that, "physics" on recordings 0-9
    # (bench/sweeps/physics-isolated-s61.json): both accuracy targets with no spurious mode on 5 of 10,
    # no operating point > 0.3 p.u. off (recording 4: 0.194 / 0.301 %, ΔQ 0.039; recording 3:
    # 1.25 / 1.30 %, spurious at ug 0.4-0.6, ΔQ 0.087); on 10-23 every model as before
    # (physics-zero-mode-s61.json). The default since stop 61
    filter_terms: str = "physics"
    # the filtered-power rows (role power) at the refinement's starts: "physics" keeps them to the
    # constant, their own state and products of two dq signals (library.power_row_mask: a low-pass
    # filter of a measured power), re-fitted to the start's own field; "any" keeps every term.
    # Why tried (stop 78): the 40 dB models' Qf rows carry controller states and cancelling pairs
    # (recording 39: -1.2e4·phi_d, 684.9·Pf*il_d - 682.5·Pf*ig_d), and Q at the model's equilibrium
    # was 0.17-0.43 p.u. off the plant's on recordings 25, 26, 38, 39. With "physics" the rows came
    # out as the plant's (recording 39: d(Qf)/dt = -31.25·Qf + 32.78·ig_d*vc_q - 31.23·ig_q*vc_d, the
    # plant's wc 31.4) and d(delta)/dt = 9.437 - 18.86·Pf. Measured on the unseen recordings 24-39
    # (bench/sweeps/power-physics-s78.json against floortol2-s77.json): both 40 dB accuracy targets
    # with no spurious mode on 8 of 16 against 9. It mends three of the four IOD misses (28
    # 0.601 -> 0.413 %, 29 0.643 -> 0.418, 36 0.840 -> 0.138) and no operating point is off (1 of 16
    # before), but it loses 25 (spurious at ug 0.2-0.6), 26, 30 (IOD 0.669), 37 (0.632), recording 35
    # breaks down (28.6 / 5.3 %, 300 coefficients), and 34 of the 160 microgrid and weak-grid
    # verdicts are wrong against 3: with the power rows clean, what they had compensated elsewhere
    # shows in the slow modes. Not the default
    power_terms: str = "any"
    # with filter_terms "physics": a grid-current row whose voltage and grid term have equal and
    # opposite coefficients within this relative tolerance at the refinement's start gets them as one
    # term, the voltage across the grid-side inductor (estimators._grid_voltage_tied); 0: off.
    # Why tried (stop 78): recording 39's ig_d row has 7506·vc_d - 7503·ug·cos(delta - theta_g) and
    # a field of 2.9 1/s at the plant's equilibrium (both voltages near 1 p.u. everywhere: the data
    # set each coefficient only to its noise, and a mismatch of 4e-4 is a bias). But it is not where
    # the IOD misses come from: over the 32 chosen models of 24-55 the ig_d row's field at the test
    # start does not go with IOD (correlation -0.12; the il_d row's 0.47), and setting the ig_d
    # row's constant so that it vanishes there (an oracle) mends none of the eight misses. Measured at 0.05 on recordings 24-39
    # (bench/sweeps/voltage-tie-s78.json): 7 of 16 within both targets with no spurious mode against
    # 9; IOD 29 0.643 -> 0.509, 36 0.840 -> 0.567, 39 0.905 -> 0.775 %, OOD 31 1.379 -> 1.144 %
    # (none enough), 34, 35, 37, 38 better, but 24 (OOD 1.051), 25 (IOD 0.900) and 27 (OOD 1.141)
    # lost, 31 and 39 spuriously unstable, 2 operating points off against 1. Not the default
    filter_voltage_tie: float = 0.0
    # stability prior of the refinement (the one-stage refinement, and the polish of the pruned model
    # on noisy data): at operating points where the plant sat at rest (refine_stability_points)
    # every eigenvalue of the model's Jacobian with a real part above -refine_stability_margin (1/s)
    # costs refine_stability_weight·(Re λ + margin)²/2; 0 switches it off. 40 ms records and 0.1 s
    # small-signal records barely see modes slower than ~10 1/s. Measured on the 40 dB benchmark
    # recording with linear integrators: without it 0.22 / 0.32 % IOD / OOD and a spurious unstable
    # mode at ug 1.1; with it (10, small-signal point) 0.20 / 0.43 %, (10, records) 0.22 / 0.55 %,
    # stable at every ug in 0.2-1.2. Applied in the growing-window stages too it cost accuracy
    # (every term kept: 1.1 / 2.3 % at weight 1000, 1.05 / 2.25 % at 10)
    refine_stability_weight: float = 10.0
    # the margin: measured (40 dB, recordings 0 / 1 / 2 / the demo's, IOD / OOD %, spurious unstable
    # modes over ug 0.2-1.1): 0.1: 0.37 / 0.55, 0.33 / 0.45, 0.48 / 2.13, 1.74 / 4.47 (0.2-0.6);
    # 0.3: demo 0.51 / 1.63 (0.2, 0.4), recording 2 0.49 / 2.21 (0.2, 0.4); 0.5: 0.40 / 0.72,
    # 0.40 / 0.75, 0.51 / 2.12, 0.70 / 2.97, none spurious. The plant's slowest pair at the records'
    # rest points: -0.73 1/s at ug 0.8, -1.55 at 1.0 (+0.25 at 1.2: the prior is soft for that).
    # Stop 19, recordings 0 / 1 / 2 / 3 / 4 / demo: 0.5: 0.40 / 0.72, 0.40 / 0.75, 0.51 / 2.12,
    # 1.13 / 1.72 (spurious at 1.0-1.1), 0.32 / 1.95, 0.70 / 2.97; 1.0: 0.42 / 0.75, 0.23 / 1.39,
    # 0.43 / 1.42, 0.98 / 1.34, 0.29 / 2.44, 0.72 / 2.78, none spurious (median OOD 1.41 against
    # 1.84 %, but one recording within the 40 dB targets against two). Not taken: 1.0 asks for more
    # damping than the plant has at ug 0.8 (-0.73), a bias toward "stable" in a stability tool
    refine_stability_margin: float = 0.5
    # the prior's weight in the growing-window stages (refine_stability_weight holds in the polish).
    # Measured with two refinement starts (40 dB, recordings 0 / 1 / 2 / demo, IOD / OOD %): 0:
    # 0.32 / 0.52, 0.30 / 0.47, 0.31 / 0.39, 1.79 / 3.26; 0.1: 0.38 / 3.60, 0.35 / 0.62, 0.75 / 1.82,
    # 0.47 / 0.68; 1: 0.95 / 1.81, 0.57 / 3.24, 0.36 / 0.56, 0.31 / 0.84
    refine_growing_stability_weight: float = 0.0
    # noisy data, a second try where the refinement went wrong: where the model the selection would
    # take scores (training error, %) above refine_rescue_ratio times what the noise alone leaves
    # (ident.noise.noise_floor_error), the first start is refined again with
    # refine_rescue_stability_weight in the growing-window stages, and that family ("... with growing
    # prior") competes in the selection; inf: off. The chosen models' ratio (stop 40's runs, 40 dB):
    # 1.2-1.9 on the benchmark's recordings within the targets and on the scenarios' but 20 kHz seed 0
    # (1.3, 1.88 / 0.27 %), 2.27 on recording 5 (0.58 / 0.60 %); above: recording 3 (2.68, 0.90 /
    # 1.43 %), 8 x 60 ms seed 1 (2.94, 0.92 / 5.87 %), 5 kHz seed 1 (4.3, 4.95 / 8.29 %; 3.9 in stop
    # 41's run). Those three with the prior in the growing stages alone (scratch, bench/candidates.py):
    # weight 0.1: 0.33 / 0.50 % (89 coefficients; it scores 2.47 against 4.30), 0.34 / 1.32 % (104;
    # 3.06 against 5.75), no better at 5 kHz (its family inconsistent with the rest points); weight 1: 0.61 / 1.72 (spurious
    # modes), 0.68 / 2.07, 1.62 / 8.53 %. With the rescue: recording 3 0.33 / 0.50 % (89), 8 x 60 ms
    # seed 1 0.34 / 1.32 % (104). Forced (ratio 0) where the fit was fine, the family wins the
    # selection and helps no more: recording 0 0.39 / 0.28 % (82; was 0.16 / 0.44 %), 4 0.33 / 2.40 %
    # (0.43 / 0.90 %), 5 0.52 / 0.50 % with a spurious unstable mode at ug 0.2 (0.58 / 0.60 %). The
    # prior is not the default itself: on recordings 0 / 1 / 2 it cost accuracy (above). Since stop
    # 46, where the chosen model still scores above the ratio after the rescue and the second start
    # was skipped (refine_starts "fallback"), the second start is refined too. Measured: protocol
    # seed 19 (bench/candidates.py, 40 dB), the first start's refinement scored 29 % and its rescue's
    # best 7.3 %; chosen before: 2.06 / 2.36 % (146 coefficients, 2.63x); now the second start's
    # round 3, 0.48 / 0.81 % (79, 1.16x), no spurious mode, in 92 s instead of 62-69 s. Of the
    # protocol's recordings 0-23 only seed 19 ends above the ratio (the others 1.1-2.3x after the
    # rescue), so no other of them changes. Since stop 65 the rescue (and the unrestricted fallback,
    # filter_terms) also runs where the model the selection would take is inconsistent with the
    # records' rest points, whatever its ratio: the scenarios' 5 kHz recording 0 at 40 dB (every
    # candidate inconsistent, 2.2x) from 4.83 / 6.29 to 0.442 / 0.236 % (estimators.PISML._noisy_rescue);
    # of the 24 protocol recordings none has such a choice, so none changes. Since stop 72 also where
    # that model is one from before the refinement (a backbone, the merged model, a re-fit): the
    # plants' vendor-c recording 2 at 40 dB from the trained backbone (2.80 / 2.91 %, 203
    # coefficients) to 0.630 / 2.79 % (88), fit 90 s against 48 s; the 24 protocol recordings' models
    # all the same (bench/sweeps/beforerefinement-s72.json against floortol-restoffset-s70.json)
    # Since stop 74 the rescue's ratio is 2.0 and the further tries (the second start after the rescue,
    # the unrestricted fallback) keep 2.5 (refine_retry_ratio). The chosen models of the 24 protocol
    # recordings at 40 dB scored 0.97-1.79x their floor where they were within both targets;
    # recording 7 (the benchmark's worst, 1.956 / 0.79 % IOD / OOD, 68 coefficients) scored 2.13x
    # and had no rescue. With the rescue at 2.0: its family's round 3, 0.278 / 0.667 % with 59
    # coefficients, W 3.6 at ug 0.8, no spurious mode, fit 103 s against 47 s
    # (`bench/candidates.py --seed 7 --noise 40 --set refine_rescue_ratio=2.0`). Of the other fits
    # recorded in the results files only the scenarios' 20 kHz recording 1 had a choice at 2.0-2.5x
    # without a rescue: 0.959 / 0.896 % to 0.153 / 2.868 % (its rescue family's round 3; outside
    # the targets either way), fit 178 s against 78 s. With the further tries at 2.0 too, the limited
    # plants' clamp recording 1 at 40 dB (2.17x after its rescue) ran both of them for the same model
    # (1.065 / 60.8 %), 242 s against 102 s: so they keep 2.5
    refine_rescue_ratio: float = 2.0
    # where the model the selection would take after the rescue still scores above this times the
    # noise floor, the second start (where it was skipped) and, with filter_terms "physics", the
    # unrestricted fallback run (estimators.PISML._noisy_rescue, _unrestricted_fallback); inf: off
    refine_retry_ratio: float = 2.5
    # Stop 73 (`bench/candidates.py ... --noise 40 --set refine_rescue_stability_weight=W`, the fits
    # where the rescue runs): 0.03 kept both of vendor-c's LCL resonances on its recording 2, 0.547 /
    # 1.10 % (64 coefficients, W 14) against 0.630 / 2.79 % (88, W 1216); protocol seed 22 0.662 /
    # 0.170 against 0.797 / 0.317 %; but vendor-c recording 0 took the unrestricted fallback, 0.233 /
    # 0.401 % with 134 coefficients (fit 195 s) against 0.182 / 0.789 % with 79, and the scenarios' 5 kHz
    # recording 1 0.945 / 0.718 % spurious at ug 0.2 against 0.614 / 0.370 %; 5 kHz recording 0 and
    # 8 x 60 ms recording 1 the same. 0.01 on vendor-c recording 2: the family blew up (inf), the
    # unrestricted fallback chosen. Mixed, and steep in the weight: not taken
    refine_rescue_stability_weight: float = 0.1
    # where the prior holds: "records" at the rest states of the small-signal and the training
    # records (a record starts where the plant sat at rest), "smallsignal" at the small-signal
    # records' only. A soft prior: a record can start at a weakly unstable equilibrium (protocol ug
    # up to 1.2, plant unstable from 1.18, +0.25 1/s at 1.2) and the data may outweigh it there.
    # Measured (40 dB, recordings 0 / 1 / 2, spurious unstable modes over ug 0.2-1.1):
    # "smallsignal" none / 0.9-1.1 / 0.2, 0.6-1.1; "records" none / none / none
    refine_stability_points: str = "records"
    # equilibrium prior of the refinement (every stage): at the same rest states, each equation's
    # f(x, u) in units of what the noise left in the rest mean makes of it (through the start
    # model's Jacobian) costs refine_equilibrium_weight·(f/σ)²/2; 0 switches it off. A record that
    # starts at rest starts at an equilibrium, which pins the integrators' equations along the
    # equilibria where 40 ms of data hardly move them. Measured (40 dB, recordings 0 / 1 / 2, one
    # start, IOD / OOD %): weight 0: 0.22 / 0.55, 0.24 / 2.16, 0.41 / 1.45 (spurious unstable at ug
    # 0.4); 0.01: 0.32 / 0.51, 0.29 / 0.49, 0.47 / 2.13, none spurious; 1: 0.48 / 3.02, 0.30 / 2.59,
    # 0.38 / 1.82; 0.03: recording 2 0.81 / 1.49. Stop 28 (the current engine, recordings 0-4, IOD /
    # OOD %, operating-point ΔQ p.u. as bench.operating_point_errors): 0.1: 0.34 / 1.40, 0.73 / 3.04,
    # 0.61 / 0.96 (spurious at ug 0.2), 0.35 / 1.21, 0.21 / 0.72; ΔQ 0.002, 0.030, 0.040, 0.060,
    # 0.002 (0.01: 0.051, 0.012, 0.036, 0.048, 0.035). Stop 43 (the current engine, bench/candidates.py,
    # recordings 0 / 2 / 5 / 6 / 7; default 0.158 / 0.438, 0.412 / 0.456, 0.575 / 0.604, 0.519 / 0.642,
    # 0.567 / 0.836): 0.1: 0.380 / 0.657, 0.835 / 0.529, 0.477 / 0.556, 0.605 / 1.42, 0.311 / 0.584
    # (3 of 5 within both targets against 2; different ones). Why it was tried: on the near misses
    # 5-7 the IOD error is a slow drift from the test's start, the plant's equilibrium at ug 1.0,
    # where the models' f is not zero (README, "Where the near misses' IOD comes from"). Stop 79, 0.1 on
    # the unseen recordings 56-71 (`bench/setting_sweep.py run --name eqweight01-s79 --set
    # refine_equilibrium_weight=0.1 --seeds 56-71`, against default-unseen-56-71-s79): 9 of 16 either
    # way (won 57, 60, 71; lost 56 and 64 to 0.96 / 1.12 and 0.33 / 1.31 %, 61 spurious at ug 0.2-0.6),
    # at most 84 coefficients 9 against 12
    refine_equilibrium_weight: float = 0.01
    # on noisy data, the polish's equilibrium prior in states instead (0: as in the other stages): at
    # each rest state the distance to the model's equilibrium next to it (J⁻¹f, a Newton step) in
    # units of the noise left in the rest mean costs refine_rest_weight·distance²/2. Multiple shooting
    # fits every window's start state, so a slow state's equilibrium can sit far from where the
    # records rested at no trajectory cost: measured (40 dB, recording 2, the chosen model) 10-200
    # noise units off in the integrators and ig_q where the plant is within 1-3. Measured (stop 26, with
    # plain couplings, recordings 1 / 2, IOD / OOD %; default 0.68 / 0.58, 0.65 / 0.41): weight 1:
    # 0.20 / 1.71 (the unpruned model chosen; the pruned ones 2.7-3.7 % IOD), 1.65 / 2.53; 0.01:
    # 1.28 / 2.30, 0.66 / 1.39; in every stage (weight 1) recording 1's growing-window fit went
    # astray (6.4 / 6.9 %). Not adopted: pinned to the rest states, the pruned models got worse.
    # Stop 44 (the current engine, bench/candidates.py), weight 0.001 on recordings 5 and 7 (default
    # 0.575 / 0.604, 0.567 / 0.836): 0.325 / 0.386 (85 coefficients, but spurious unstable at ug 0.2
    # and 0.4), 0.900 / 2.19 (124); both chose the rescue's family. Nor does the misfit it measures
    # predict the test: over the 16 recordings' sound candidates the equilibria sit 2-560 noise units
    # (rms) from the rest means, and recording 11's, at 2-3 (the plant's 1-3), score 0.57-1.0 % IOD.
    # Stop 79 (the current engine, recordings 40-55 at 40 dB, `bench/setting_sweep.py run --name
    # restweight-s79 --set refine_rest_weight=0.01 --seeds 40-55`, against default-unseen-40-55-s78):
    # 8 of 16 within both targets against 10, at most 84 coefficients 10 against 15; 46, 50 and 51
    # broke (1.2-2.2 % IOD, 1.3-3.6 % OOD), of the IOD misses only 54 mended (0.732 -> 0.331 %)
    refine_rest_weight: float = 0.0
    # on noisy data, the refinement's windows that lie inside a record's steady start begin at its rest
    # mean: a prior of this weight times the rest's samples (in the noise's units, the windows' scale)
    # holds their start states there (trajfit._ShootingProblem.rest_starts); 0: off, free starts.
    # Why: the plant holds its rest state, and 13 of the 18 misses among stop 102's 48 unseen 40 dB
    # recordings (512-559) were models that, run from the plant's rest at ug 1.0, moved the d-axis
    # grid current by 4.5e-3 p.u. or more in the 8 ms before the IOD record's phase jump (none of the
    # 30 within the targets did; bench/candidates.py's "rest_hold"). With free starts a window inside
    # a rest moves its start to meet a model's drift. Measured (stop 103, `bench/candidates.py --seed S
    # --noise 40 --set refine_rest_starts=1`, against the defaults' tables: stop 102's on 528-559,
    # stop 103's on 560-575, fitted on the same machine): within both accuracy targets with no
    # spurious mode 32 of 48 against 27 (won 529, 532, 536, 538, 539, 543, 552, 556, 557, 561, 564,
    # 571, 572; lost 531, 534, 535, 540, 542, 551, 567, 570); the chosen models' drift before the
    # jump mean 2.7e-3 against 3.5e-3 p.u., IOD / OOD median 0.35 / 0.36 against 0.37 / 0.44 %; any
    # candidate within them (an oracle) 45 of 48 against 42; fits median 57.6 s against 58.4 s
    refine_rest_starts: float = 1.0
    # ridge prior of the refinement (every stage; noisy data only since stop 44): each coefficient's share of
    # its equation, c_ij·rms(term i)/rms(f_j) over the fitted samples (f: the start model), costs
    # refine_ridge_weight·share²/2 (trajfit.TrajectoryFitter.fit); 0 switches it off. Why tried:
    # at 40 dB the refined rows keep pairs that cancel along the records (delta and sin(delta) at
    # -1.59e4 / +1.60e4 in the Qf row of recording 3's model). Measured (stop 35, 40 dB, benchmark
    # recordings 0-4, IOD / OOD %, coefficients; off: 0.16 / 0.44 (78), 0.40 / 0.69 (90),
    # 0.41 / 0.46 (95), 0.90 / 1.43 (149), 0.43 / 0.90 (175)): 3e-4: 0.80 / 0.94 (82),
    # 0.27 / 0.42 (78), 0.38 / 0.59 (74), 0.35 / 0.76 (109), 0.72 / 5.53 (102); 1e-3: 0.17 / 0.93
    # (85), 0.55 / 0.77 (86), 0.40 / 0.31 (83), 0.47 / 0.74 (95), 0.63 / 6.97 (119); 1e-2 on
    # recording 3: 1.82 / 3.57. Sparser models, lower free-run training errors (1.7-2.4 % against
    # 2.2-4.3 %), cleaner angle and power rows (recording 0 at 3e-4: d(delta)/dt = 9.407 - 18.83·Pf,
    # the plant's 9.42 - 18.85·Pf), recording 3 within both targets at either weight; but a sag
    # to 0.4 p.u. outside the data gone wrong on recording 4 (OOD 5.5-7.0 %) and one more recording
    # outside the targets: 3 of 5 within both at either weight, as against 4 of 5. Recordings 5-9
    # (off / 3e-4): 0.58 / 0.60 (114) / 0.46 / 0.50 (89), 0.52 / 0.64 (93) / 0.74 / 0.62 (77),
    # 0.57 / 0.84 (89) / 0.16 / 0.94 (78), 0.21 / 0.26 (107) / 0.65 / 0.17 (78), 0.29 / 0.46 (110) /
    # 0.32 / 0.89 (97): over the ten, 6 within both targets either way (different ones), 84
    # coefficients or fewer (the issue's 250× compression) on 1 against 5, W at ug 0.8 median 5.9
    # against 3.5; the worst OOD 1.43 against 5.53 %. Not the default. Stop 44 (the current engine,
    # bench/setting_sweep.py, the rows in bench/sweeps/; recordings 0-15, the engine never tuned on
    # 10-15; "ok": both 40 dB targets and no spurious mode): default 9 of 16 ok (7 of 0-9, 2 of
    # 10-15), IOD / OOD median 0.37 / 0.62 %, worst 0.58 / 1.31 %, 84 coefficients or fewer on 1;
    # 3e-4: 8 of 16 ok, median 0.46 / 0.82 %, worst OOD 5.53 % (recording 4 again), 84 or fewer on 9;
    # 1e-4: 12 of 16 ok (7 of 0-9, 5 of 10-15), median 0.25 / 0.56 %, 84 or fewer on 7, but worse
    # tails: recording 0 1.03 / 2.41 % (default 0.16 / 0.44), 6 1.13 / 0.51 (0.52 / 0.64), 9 0.34 /
    # 1.21 (0.29 / 0.46). Recordings 16-23 (never looked at before): 0: 4 of 8 ok (3 with spurious
    # modes, recording 19 2.06 / 2.36 %), 1e-4: 3 of 8 ok (3 spurious, worst 0.74 / 1.37 %), 84 or
    # fewer on 4 against 0. Over the 24: 15 ok against 13, 84 coefficients or fewer on 11 against 1,
    # every 40 dB target on one recording 7 against 1, IOD / OOD median 0.29 / 0.56 % against
    # 0.31 / 0.62 %, worst 1.13 / 2.41 % against 2.06 / 2.36 %; fit times on 16-23 median 57 s
    # against 61 s. But on the other inverters (make bench-plants, 40 dB, recordings 0-2) 1e-4 met
    # both targets on 0 of 6 vendor-b / vendor-c recordings against 2 (vendor-b 0.517 / 0.384 with
    # a spurious mode, 0.186 / 2.08, 0.613 / 2.19; vendor-c 0.281 / 1.07, 0.98 / 2.62, 0.60 / 3.07),
    # and on the scenarios' first five 40 dB rows 1 of 5 against 4 (20 kHz 0.602 / 0.347, 0.372 /
    # 1.27; 5 kHz seed 0 1.22 / 2.37 with spurious modes). Off again: more compression, less
    # robust off the protocol. On noisy records only (estimators._ridge_weight)
    refine_ridge_weight: float = 0.0
    # where the refinement wins the selection, the sparsest pruned candidate whose free-run training
    # error is within this fraction of the refined model's (of the best, where the refined model does
    # not compete: stop 40) is the explicit model. Measured as a knob (stop 40; the candidates'
    # scores are in the benchmarks' recorded selections, `selection` in bench/*results.json): the
    # scenarios' 40 dB 20 kHz seed 0 chose "pruned +0.1 % x3" (82 coefficients, 2.140 %; 1.88 /
    # 0.266 % IOD / OOD) against the refined model's 1.782 % and the best, "pruned +0.1 %" (129,
    # 1.771 %; 0.373 / 0.493 %): only a tolerance below 0.201 passes it over. On the ten 40 dB
    # benchmark recordings the chosen models score up to 1.077x the best eligible model of their
    # family (recording 7; 1.043 and 1.025 on recordings 9 and 8), and below that a less pruned one
    # wins (recording 7: 0.46 / 1.02 % with 109 coefficients, or 0.41 / 1.02 % with 134, instead of
    # 0.57 / 0.84 % with 89). The window that serves both is set by one recording on each side: not
    # a setting to tune on. (Stop 42: that 20 kHz row's round 2 had lost the fit, and
    # selection_round_rise now passes its rounds 2 and 3 over.)
    selection_tolerance: float = 0.5
    # on noisy records the tolerance above measures the part of each score above the records' noise
    # floor (ident.noise.noise_floor_error: what a model of the noise-free states would score):
    # a pruned candidate is near the reference if its score minus the floor is within (1 + this) x
    # the reference's; inf: off (selection_tolerance on the whole scores, as on clean records). Why:
    # at 40 dB the floor is 1.5-2 % of scores of 2-3 %, so a relative tolerance on the whole score
    # lets a pruned model whose own error is 2-3x the reference's pass as near (stop 70,
    # bench/candidates.py on the 24 protocol recordings at 40 dB: recording 2 chose "pruned +0.1 %",
    # 3.17 % against the refined model's 2.20 %, floor ~1.6: 1.67 / 2.06 % IOD / OOD). Replayed on
    # those tables (scratch, the engine's own _configured_selection): 0.5, 1.0 and 1.5 take 19 of 24
    # within both accuracy targets with no spurious mode against 17 (2 and 3 mended, none lost),
    # 2.0 18; on the whole scores 0.2-0.3 take 18 (2 mended). Measured (`bench/setting_sweep.py run
    # --name floortol-restoffset-s70 --set selection_floor_tolerance=1.0 --set
    # selection_rest_offset=0.3`, the defaults since stop 70, against longbranch-restoffset-s69.json):
    # 19 of 24 against 17 (2: 0.427 / 0.474 %, 3: 0.291 / 0.466 %; 18 another model within them),
    # every target 15 against 14, OOD worst 1.22 % against 2.06, no spurious mode, no operating
    # point off; microgrid / weak-line verdicts 32 of 240 wrong against 29 (24 flagged against 21,
    # 5 right ones flagged against 0); fits median 43.9 s, worst 70 s. Since stop 77 2.0: at 1.0 the
    # cut is tight where the refined model's own share is small, and a 213-coefficient refined model
    # spuriously unstable at ug 1.1 stood (protocol recording 32, never looked at before: refined at
    # long windows 1.922 %, floor 1.76; its first prune round at 2.180 %, 2.6x the share: 0.206 /
    # 0.858 % -> 0.076 / 0.158 %, 93 coefficients). Measured (`bench/setting_sweep.py run --name
    # floortol2-s77 --set selection_floor_tolerance=2.0 --seeds 24-39,0-23 --noise 40`, against
    # default-0-23-s76.json and default-unseen-24-39-s77.json, the same engine's candidate tables; the
    # replay had said the same): 30 of 40 within both targets with no spurious mode against 29 (32
    # mended, none lost), at most 84 coefficients 34 against 33 (recording 20: 85 -> 70, 0.253 / 0.343
    # -> 0.352 / 0.417 %; 27: 74 -> 64), every other model the same, fits median 42.6 s. The risk is
    # stop 70's recording 2 above (2.6x its refined model's share, chosen at 2.0): today's engine
    # builds other candidates there and keeps its 0.427 / 0.474 %. Elsewhere (make bench-plants,
    # make bench-scenarios' 40 dB rows): vendor-c recording 1 lost to a sparser round (0.428 / 0.895 %,
    # 71 coefficients -> 0.915 / 0.642 %, 57), the scenarios 9 of 22 as before: even on accuracy over
    # the three benchmarks, sparser on four fits. Checked at stop 78 on recordings no rule had been
    # made on (seeds 40-55, bench/sweeps/default-unseen-40-55-s78.json; bench/selection_replay.py on
    # their candidate tables with 1.0): 10 of 16 against 9 (recording 48: 1.0 takes the refined model,
    # 217 coefficients, outside the targets; 2.0 its third prune round, 0.143 / 0.299 %, 61), none
    # lost, three more sparser (41: 71 -> 64, 43: 83 -> 55, 46: 79 -> 73)
    selection_floor_tolerance: float = 2.0
    # a prune round (``pruned +B % xR``) whose free-run error on the scoring records rises above
    # (1 + this) x the round before it is lost, and so are the rounds built on it: none of them is
    # taken as the sparser model near the best, unless it is the best (selection._lost_rounds);
    # inf: off. Why: each round
    # drops what its shooting windows' quadratic cost model says costs +0.1 % (scaled by the
    # samples), and where a free run over the whole records then loses much more, the pruning
    # dropped a term the records need. Measured (stop 42, the recorded selections of the 38 40 dB
    # PISML fits, with and without the Jacobian loss, of bench/results.json, scenarios_results.json
    # and plants_results.json): the round-to-round ratio is 0.34-1.26 (85 rounds) where nothing went
    # wrong, 1.40-4.89 where a round lost the fit (8 families of 7 fits; never the best candidate).
    # Only one chosen model changes at any setting in 0.26-0.57: the scenarios' 20 kHz seed 0 had
    # x2 at 1.58x x1 (IOD 3.14 %, the d-axis grid current 7.9 % off after the phase jump) and chose
    # x3 (2.14 against 1.77 %, within the tolerance: 1.88 / 0.266 % IOD / OOD, 82 coefficients);
    # with the rule x1, 0.373 / 0.493 % (129). Where a sparser round scored worse but was sound it is
    # kept: 20 kHz seed 1 (x3 1.25x x2: 0.328 / 0.944 %; x2 would give 0.139 / 2.51 %), the rescue
    # family of recording 3 (1.23x: 0.329 / 0.497 %)
    selection_round_rise: float = 0.35
    # a candidate whose equilibrium at a point where a training record sat at rest has a mode growing
    # faster than this (1/s) counts as inconsistent there, as one with no equilibrium there that,
    # run freely from the rest state, moves more than 10 % within 1 / this seconds (a fold just
    # before the point is excused where it is passed as slowly; selection._inconsistent_points);
    # the candidates with the fewest such points compete (the plant's own boundary mode: +0.25 1/s
    # at ug 1.2). Where the small-signal records sat at rest a mode that does not decay counts (stop
    # 39): they are perturbations about an equilibrium they return to. Stop 81, replayed on the 80
    # candidate tables of the unseen recordings 24-71 and 88-119 (`bench/selection_replay.py ... --set
    # selection_unstable_rate=0.5`): 0.5 1/s 43 of 80 within both accuracy targets with no spurious
    # mode, 0.3 and 0 42, against the default's 44 replayed. Why tried: recording 113's chosen model
    # grows at +0.2, +0.4 and +0.9 1/s at its rest points at ug 1.00, 1.04 and 1.14 (spurious at ug 1.0
    # and 1.1, where the plant decays); no tighter allowance chooses better on balance. Kept
    selection_unstable_rate: float = 1.0
    # a candidate whose equilibrium at a point where a training record sat at rest lies farther than
    # this from the rest state (‖x_eq − x_rest‖ / ‖x_rest‖, as the drift above) counts as inconsistent
    # there too; inf: off. The record sat still there, so the plant's equilibrium is there within the
    # noise; a model whose equilibrium is elsewhere answers the operating-point question wrongly
    # (stop 69, bench/candidates.py at 40 dB: recording 3's long-window rounds 0.8-2.0, their
    # operating point 3.5 p.u. off in Q; the chosen models of recordings 2 and 6 0.007 and 0.04;
    # measured with refine_long_branch, see there). Since stop 70 0.3 (was 0.1): the scenarios' 8
    # records of 60 ms seed 0 at 40 dB had a pruned model at 0.378 / 0.340 % IOD / OOD (69
    # coefficients, no spurious mode) inconsistent only through 0.113 at one rest point (every other
    # refined candidate at 6-9 points), so the trained backbone was chosen, 5.46 / 7.91 % (bench/candidates.py
    # replayed; on the 24 protocol recordings 0.2-0.5 change no choice's verdict, recordings 18 and 20
    # take other models within both targets)
    selection_rest_offset: float = 0.3
    # grid voltages (the grid-magnitude role; grid phase 0) where a power engineer will ask for the
    # model's operating point: where the selected candidate has no equilibrium at some of them (as
    # the analysis finds it, from the rest points) and another candidate as consistent with the rest
    # points has one at more, the selection is made again among those with the fewest missing
    # (selection._selected). Measured (stop 34, 40 dB, benchmark recording 4): the chosen model
    # (140 coefficients, 0.63 / 0.73 % IOD / OOD) folded at ug 0.767 and had none at 0.2-0.6; the
    # other candidate consistent with every rest point (175, scored 3.36 % against 2.96 %) has one
    # everywhere: 0.43 / 0.90 %. Empty: no such check. Stop 80, replayed empty on the 64 candidate tables
    # of the unseen recordings 24-71 and 88-103 (`bench/selection_replay.py ... --set
    # selection_equilibrium_grid=`): 36 of 64 within both accuracy targets with no spurious mode against
    # the default's 35 (won 98; 34, 57 and 69 re-chosen on the same side of the targets). Recording 98's
    # winner has no equilibrium at ug 0.2 and 0.4 as the analysis searches for one: an operating-point
    # question it cannot answer. Kept
    selection_equilibrium_grid: tuple = (0.2, 0.4, 0.6, 0.8, 1.0, 1.2)
    # the sparser model near the best is not one unstable at a grid voltage of
    # selection_equilibrium_grid where the best is stable (selection._chosen_among): what its
    # pruning dropped, at no cost the records can see, flipped the analysis' verdict where they say
    # nothing. Measured (stop 43, 40 dB): on the bench/candidates.py tables of the benchmark's ten
    # recordings, protocol seeds 10-15 and four scenario fits, replayed, it changed one choice of
    # twenty, seed 14's ("pruned +0.1 % x2", unstable at ug 0.2 and 0.4 where the plant is at -0.22
    # and -0.31 1/s, 0.325 / 1.129 % IOD / OOD -> the best, stable everywhere, 0.305 / 1.068 %);
    # `make bench` with it on: every model as without (it passed nothing over). But the scenarios'
    # ug0 0.6-1.0 seed 1 lost: its rounds 2 and 3 were unstable at ug 1.2, where the plant is too
    # (+0.25 1/s), and the best stable there, so it took the best, 0.705 / 1.02 % (141
    # coefficients) instead of 0.450 / 0.790 % (97). Asked both ways (also stable where the best is
    # unstable) it would have changed three replayed choices for the worse (20 kHz seed 1:
    # 0.190 / 3.66 % instead of 0.328 / 0.944 %). One mended, one broken: the data do not decide a
    # slow mode's sign out there, and no direction of this rule does. Not the default. Stop 78,
    # replayed on the unseen recordings 40-55: 10 of 16 as without (44, 45, 50 re-chosen, none across
    # the targets; 50 takes 120 coefficients against 80). Stop 97, replayed on the 48 unseen tables of
    # 320-367 (`bench/selection_replay.py TABLES --set selection_grid_stability=true`): 29 of 48 within both
    # accuracy targets with no spurious mode against 28 (347 mended: spurious at ug 0.2 -> 0.139 / 0.164 %,
    # but 97 coefficients against 71; 338 re-chosen within; nothing on 352-367), at most 84 coefficients 39
    # against 40; `selection_floor_tolerance=5.0` changed no count on 320-351 (21 of 32)
    selection_grid_stability: bool = False
    # on low-SNR records (low_snr_below_db), the eligible candidates whose multiple-shooting cost
    # over windows of SELECTION_WINDOW samples (coefficients fixed, each window's start state fitted:
    # trajfit.window_costs) exceeds the lowest one's by more than this, as a chi-square (2 (window + 1)
    # times the cost difference: the squared misfit in noise units), do not compete; 0 or inf: off.
    # Why (stop 94, 30 dB, candidate tables of 184-191 with refine_growing_windows_low_snr=20,50,100):
    # the rescue's family had lost one of the two LCL resonances (W 1300-1470 at ug 0.8, one pair of
    # modes at -650 ± 9150j 1/s gone to the real axis or to -730 ± 740j) and reproduced the records run
    # freely better (185: 4.9 against 7.6-51 %; 187: 5.2-9.7 against 6.4-48 %), but the 1 ms windows
    # 550-2200 worse, where the first family's candidates lie within 110 of each other with 60-230
    # coefficients. Replayed there: 185 1.168 / 6.613 % (W 1412) -> 0.928 / 1.745 % (W 35), 187
    # 2.274 / 7.005 % (W 1314) -> 1.265 / 2.169 % (W 19), the other six as chosen (150 also changes 189,
    # 1.259 / 1.402 -> 1.133 / 0.778 %; 600 and 1000 as 300). With the default windows, fitted
    # (`bench/candidates.py --seed S --noise 30`, 296-303 unseen): it changes 303 alone, 1.378 / 5.326 %
    # (219 coefficients, W 1318, spurious at ug 0.2 and 0.4) -> 1.192 / 1.736 % (77, W 32, none), the
    # table's best candidate; the other seven chose as without it (`snr30-unseen-296-303-s94-before`;
    # the rows: bench/sweeps/snr30-window-check-s94.json); on 184-191 (the
    # same, stop 84's sweep's recordings) it took out 0-7 candidates a fit and changed no choice. The
    # 40 dB protocol (floor 1.2-2.0 %) never runs it: its fits are as before to the bit (224's table).
    # Forced on at 40 dB (`bench/candidates.py --seed S --noise 40 --set low_snr_noise_floor=0`, 224-239; since
    # stop 96 low_snr_below_db=inf):
    # it took out one candidate on 231 and one on 235, changed no choice (10 of 16 within either way)
    selection_window_excess: float = 300.0
    # on noisy records, where the chosen model's slowest mode at the small-signal records' rest points
    # decays slower than this (1/s) and eligible candidates within selection_floor_tolerance of the
    # best score decay at least this fast there, the choice is made again among those
    # (selection._decay_rechoice); 0: off. The records cannot tell -0.03 1/s from -0.5 (0.1 s of
    # small-signal record), but a pruning that dropped an integrator's feedback leaves the first.
    # Measured (stop 75, bench/candidates.py on the 24 protocol recordings at 40 dB, the choice
    # replayed with the engine's own selection): three chosen models decayed slower than 0.19 1/s
    # there, all at -0.03 to -0.04 (the plant: -0.73 at ug 0.8), and every margin in 0.05-0.19
    # re-chooses those three and no other: recording 1 0.278 / 1.224 % IOD / OOD -> 0.269 / 0.546 %
    # (64 coefficients), 3 0.564 / 0.898 -> 0.376 / 0.607 (127), 18 0.229 / 0.881 -> 0.179 / 0.434
    # (61), none with a spurious mode: 21 of 24 within both accuracy targets against 19. At 0.2
    # recording 2 (-0.19) would take its refined model (207 coefficients). Recording 1's new model
    # has no equilibrium at ug 1.2, where its old one was unstable (+0.55 1/s; the plant +0.25): the
    # re-choice may lose an operating point only where the choice was unstable
    selection_decay_margin: float = 0.1
    # on noisy records, where the chosen model is unstable at a grid voltage of selection_equilibrium_grid
    # below every point where a record sat at rest, and eligible candidates within
    # selection_floor_tolerance of the best score are stable there (and keep the choice's operating
    # points and small-signal decay), the choice is made again among those (selection._stability_rechoice;
    # the model passed over stays one of the model's alternatives, so the analysis reports there that
    # the records do not decide the verdict); false: off. Why: 40 ms records resting at ug 0.8-1.2 do
    # not pin the slow voltage-controller mode at low grid voltages (the plant: -0.22 +- 0.91j 1/s at
    # ug 0.2), and which pruned candidate puts it on the wrong side of the axis there is a lottery: 18
    # of the 104 unseen 40 dB fits 320-423 chose a model spuriously unstable at ug 0.2-0.6 while others
    # as good on the records were stable there. Measured (stop 100, `bench/selection_replay.py TABLES
    # --set selection_stability_rechoice=true` on the candidate tables of those 104, fitted with the
    # defaults of stops 97-99): 63 of 104 within both 40 dB accuracy targets with no spurious mode
    # against 60 (347, 356, 378 mended, none lost), spurious 9 against 18, at most 84 coefficients 82
    # against 86; two fits already outside the targets got worse out of distribution (414: 0.299 /
    # 0.543 % spurious at 0.2-0.6 -> 0.600 / 9.740 %; 372 1.47 / 1.74 -> 2.47 / 5.85 %). Checked on 32
    # recordings fitted afterwards and never looked at before (424-455,
    # `bench/sweeps/default-unseen-424-455-s100.json`): 23 of 32 against 21 (432, 444 mended, none
    # lost), spurious 2 against 4; 456-471, fitted with it (`default-unseen-456-471-s100.json`): 9 of 16,
    # where it fired on 456 and 463, both within the targets (7 of 16 replayed without it). Own-model
    # 3-bus / weak-line verdicts (bench/microgrid_bench.py's quick_verdicts) wrong on 24 of the 136 recordings against
    # 25 (356, 369, 432 mended; 372 and 414 broken, both outside the accuracy targets either way). Refitted with the
    # rule on (bench/candidates.py), 8 of the 11 recordings whose choice it changes (341, 347, 356, 369, 378, 414,
    # 432, 444) chose as replayed. On this plant the rule cannot cost a recording both targets (it fires only where
    # the choice has a spurious mode); on a plant truly unstable at low ug it would hide that only where the records
    # cannot tell, and the alternatives then say so
    selection_stability_rechoice: bool = True
    # the chosen model carries a warning (selection "warnings", printed by `pisml identify`, logged by
    # the identifier node) where its free-run error on the scoring records is above this ratio times
    # what their noise alone leaves (ident.noise.noise_floor_error) plus selection_warn_noise_margin
    # percentage points (which clean records, floor ~0, need); inf: never. Calibrated (stop 45) on
    # the 60 PISML fits recorded in bench/results.json, scenarios_results.json and
    # plants_results.json: the chosen models within the issue's targets score at most 2.37x the
    # floor (clean: at most 0.04 %); it flags three fits (saturation plant clean 6.7 %, 10.2 / 62.5 %
    # IOD / OOD; saturation 40 dB 6.3x, 5.2 / 62.9 %; the scenarios' 5 kHz seed 1 3.9x, 4.6 / 8.0 %),
    # and 20 dB (3.4x, 9.1 / 11.8 %) has the hold's warning already. It does not see the 40 dB
    # failures that score near the floor (vendor-c seeds 1 and 2 at 1.3-1.4x, 1.2 / 7.7 and
    # 2.8 / 2.9 %; 30 dB at 1.5x, 1.4 / 1.9 %). Stop 46 added the protocol's recordings 10-23 (the
    # engine was not tuned on them): the chosen models scored 1.13-1.95x their floor except seed 19,
    # 2.63x (4.86 % against 1.85 %; 2.06 / 2.36 % IOD / OOD, a refinement that went wrong and a
    # rescue that did not mend it), which 3x + 0.5 did not flag. Since stop 46 2.5x + 0.1 points:
    # the further tries' own trigger (refine_retry_ratio), so a model still above it after them is
    # flagged; it flags seed 19 (threshold 4.72 %) and none of the sound fits (the 2.37x one,
    # jumps 10-20° seed 0 at 40 dB: 4.34 % against a threshold of 4.68 %; clean ones score at most
    # 0.04 % against 0.1). The same three of the 60 recorded fits as 3x + 0.5, and on clean data it
    # also speaks up between 0.1 and 0.5 %, where the clean targets (0.05 / 0.1 %) are missed. (Seed
    # 19 itself is mended since stop 46 by the second start after the rescue, refine_retry_ratio)
    # search the records for a limit of a dq reference (a current limit: ident.limiter; every fit since
    # stop 56, 2-9 s, reported by limiter.limit_note) and, where the model the selection would take
    # scores above the caution's threshold below (ratio x noise floor + margin), refine a family with
    # its terms (estimators.PISML._limiter_family).
    # Measured (stop 54, scratch /tmp/sat/run.py, the benchmark's saturation plant, IOD / OOD %):
    # clean recording 0 10.2 / 62.5 -> 0.022 / 0.093 (limit 2.2000 against 2.2); 40 dB recording 0
    # 5.23 / 62.9 -> 1.48 / 5.46 (one start, the model re-fitted with the terms: 0.94 / 7.44; with the
    # plant's own reference and limit instead of the fitted ones 0.36 / 1.07), recording 1
    # 2.93 / 165 -> 2.29 / 7.50. On the default plant no fit reaches the threshold: no family runs
    limiter_search: bool = True
    # samples per integral-form window of that search. Measured (stop 54, saturation plant at 40 dB,
    # recording 0; error of the fitted limited reference on the test records, rms, against 1.13): 10:
    # 0.24, 20: 0.045, 40: 0.085
    limiter_span: int = 20
    # refine_rest_weight of the polish in the limiter family's refinement (the rest of the fit keeps
    # refine_rest_weight). Why: with a current limit near the records' rest currents (the saturation
    # plant, |il| 2.07 of 2.2 at ug 0.8), the family's refined and pruned models put their
    # equilibria 1.7-3.2 p.u. from the records' rest states and were inconsistent with all 9 of
    # them, so a model without the limit was chosen. Measured (stop 65, bench/candidates.py --plant
    # saturation --noise 40, IOD / OOD %): recording 0: 0 -> 5.23 / 62.9 (the unrestricted family's
    # model chosen), 0.1 -> 1.57 / 3.24, 1 -> 1.79 / 3.16 (the family's round 3, consistent at every
    # point); recording 1: 0 -> 0.994 / 12.5, 0.1 -> 1.15 / 11.5, 1 -> 1.89 / 18.0
    limiter_rest_weight: float = 0.1
    selection_warn_noise_ratio: float = 2.5
    selection_warn_noise_margin: float = 0.1

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any] | None) -> "IdentConfig":
        """Build from a mapping (unknown keys raise :class:`ConfigError` naming them)."""
        values = dict(values or {})
        known = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ConfigError(f"identification config: unknown key(s) {unknown}; known: {sorted(known)}")
        kwargs = {}
        defaults = cls()
        for key, value in values.items():
            if key == "roles":
                kwargs[key] = value if isinstance(value, SignalRoles) else SignalRoles.from_mapping(value or {})
                continue
            default = getattr(defaults, key)
            try:
                if isinstance(default, bool):
                    if isinstance(value, str):
                        if value.lower() not in ("true", "false", "1", "0", "yes", "no"):
                            raise ValueError(value)
                        value = value.lower() in ("true", "1", "yes")
                    kwargs[key] = bool(value)
                elif isinstance(default, tuple):
                    element = type(default[0]) if default else float
                    parts = [v for v in value.split(",") if v.strip()] if isinstance(value, str) else value
                    kwargs[key] = tuple(element(v) for v in parts)
                else:
                    kwargs[key] = type(default)(value)
            except (TypeError, ValueError):
                raise ConfigError(f"identification config: {key} = {value!r} is not a valid "
                                  f"{type(default).__name__}") from None
        config = cls(**kwargs)
        config.check()
        return config

    @classmethod
    def load(cls, path: str | Path | None, overrides: Mapping[str, Any] | None = None) -> "IdentConfig":
        """From a YAML/JSON file (its ``identification:`` section if present), then ``overrides``."""
        values: dict = {}
        if path:
            import yaml

            path = Path(path)
            try:
                data = yaml.safe_load(path.read_text()) or {}
            except (OSError, yaml.YAMLError) as err:
                raise ConfigError(f"{path}: cannot read identification config: {err}") from None
            if not isinstance(data, dict):
                raise ConfigError(f"{path}: expected a mapping of settings")
            values = dict(data.get("identification", data))
        values.update(overrides or {})
        return cls.from_mapping(values)

    def check(self) -> None:
        positive = ["backbone_span", "epochs", "window", "batch_windows", "substeps", "distill_samples", "distill_max_terms",
                    "refine_window", "refine_max_windows", "learning_rate", "refit_span", "refine_growing_substeps",
                    "refine_prune_rounds", "refine_long_branch_evaluations", "node_epochs", "node_learning_rate",
                    "limiter_span", "refine_polish_damping", "residual_fits"]
        for key in positive:
            if getattr(self, key) <= 0:
                raise ConfigError(f"identification config: {key} must be > 0, got {getattr(self, key)}")
        for key in ["backbone_threshold", "backbone_alpha", "backbone_span_max_s", "coupling_min_separation", "dropout",
                    "lambda_pert", "lambda_sparse",
                    "distill_threshold", "distill_spread", "refine_max_nfev", "selection_tolerance", "selection_unstable_rate",
                    "selection_rest_offset",
                    "refine_stability_weight", "refine_stability_margin", "refine_equilibrium_weight",
                    "refine_growing_stability_weight", "refine_stage_prune_budget", "refine_stage_tolerance",
                    "refine_single_precision_stages",
                    "refine_prune_reference_samples", "refine_rest_weight", "limiter_rest_weight",
                    "refine_rest_starts",
                    "refine_prune_zero_mode",
                    "refine_ridge_weight", "refine_max_step", "clean_growing_error",
                    "weight_decay", "node_weight_decay"]:
            if getattr(self, key) < 0:
                raise ConfigError(f"identification config: {key} must be >= 0, got {getattr(self, key)}")
        if not re.fullmatch(r"cpu|auto|cuda(:\d+)?", self.device):
            raise ConfigError(f"identification config: device must be cpu, auto or cuda[:N], got {self.device!r}")
        if any(b < 0 for b in self.refine_prune_budgets):
            raise ConfigError(f"identification config: refine_prune_budgets must be >= 0, got "
                              f"{list(self.refine_prune_budgets)}")
        low, low_evaluations = self.refine_growing_windows_low_snr, self.refine_growing_evaluations_low_snr
        if low_evaluations and not low:
            raise ConfigError(f"identification config: refine_growing_evaluations_low_snr {list(low_evaluations)} "
                              f"needs refine_growing_windows_low_snr (empty)")
        evaluations = low_evaluations or self.refine_growing_evaluations
        if low and (len(low) != len(evaluations) or any(v <= 0 for v in (*low, *evaluations))):
            raise ConfigError(f"identification config: refine_growing_windows_low_snr must be empty or one positive "
                              f"window per stage of refine_growing_evaluations_low_snr (or, empty, of "
                              f"refine_growing_evaluations) {list(evaluations)}, got {list(low)}")
        self.refine_growing_windows_low_snr = tuple(int(v) for v in low)
        self.refine_growing_evaluations_low_snr = tuple(int(v) for v in low_evaluations)
        for stages in ("growing", "polish"):
            windows, evaluations = (getattr(self, f"refine_{stages}_{k}") for k in ("windows", "evaluations"))
            if windows and (len(windows) != len(evaluations) or any(v <= 0 for v in (*windows, *evaluations))):
                raise ConfigError(f"identification config: refine_{stages}_windows and refine_{stages}_evaluations "
                                  f"must be equally long lists of positive integers, got {list(windows)} and "
                                  f"{list(evaluations)}")
        if self.refine_growing_max_windows and (len(self.refine_growing_max_windows) != len(self.refine_growing_windows)
                                                or any(not (v >= 0 and v == int(v)) for v in self.refine_growing_max_windows)):
            raise ConfigError(f"identification config: refine_growing_max_windows must be empty or one count >= 0 "
                              f"(0: all) per growing-window stage {list(self.refine_growing_windows)}, got "
                              f"{list(self.refine_growing_max_windows)}")
        self.refine_growing_max_windows = tuple(int(v) for v in self.refine_growing_max_windows)
        if not all(math.isfinite(g) and g > 0 for g in self.selection_equilibrium_grid):
            raise ConfigError(f"identification config: selection_equilibrium_grid must hold positive grid "
                              f"voltages, got {list(self.selection_equilibrium_grid)}")
        if any(b < 0 for b in self.refit_budgets):
            raise ConfigError(f"identification config: refit_budgets must be >= 0, got {list(self.refit_budgets)}")
        if not self.refine_prune_degree_preference >= 1:  # also NaN
            raise ConfigError(f"identification config: refine_prune_degree_preference must be >= 1, got "
                              f"{self.refine_prune_degree_preference}")
        if 0 < self.refine_max_step < 1e-7:
            raise ConfigError(f"identification config: refine_max_step must be 0 (off) or at least 1e-7 s, got "
                              f"{self.refine_max_step}")
        for key in ("refine_rescue_ratio", "refine_retry_ratio", "refine_rescue_stability_weight",
                    "selection_round_rise", "selection_warn_noise_ratio", "selection_warn_noise_margin",
                    "selection_floor_tolerance", "selection_window_excess"):
            if not getattr(self, key) >= 0:  # also NaN, which would switch the rescue or the rule off unseen
                raise ConfigError(f"identification config: {key} must be >= 0 (inf: off), got {getattr(self, key)}")
        if not self.low_snr_below_db >= 0:  # also NaN
            raise ConfigError(f"identification config: low_snr_below_db must be an SNR in dB >= 0 (0: no records "
                              f"count as low-SNR), got {self.low_snr_below_db}")
        if not (math.isfinite(self.selection_decay_margin) and self.selection_decay_margin >= 0):
            raise ConfigError(f"identification config: selection_decay_margin must be a rate >= 0 (1/s; 0: off), "
                              f"got {self.selection_decay_margin}")
        if not 0 <= self.dropout < 1:
            raise ConfigError(f"identification config: dropout must be in [0, 1), got {self.dropout}")
        if self.integrator_terms not in ("linear", "error", "cascade", "any"):
            raise ConfigError(f"identification config: integrator_terms must be linear, error, cascade or any, "
                              f"got {self.integrator_terms!r}")
        if not (self.input_interval_threshold >= 0 and self.input_edge_width >= 0):
            raise ConfigError(f"identification config: input_interval_threshold and input_edge_width must be >= 0 "
                              f"(0: off), got {self.input_interval_threshold} and {self.input_edge_width}")
        if self.input_denoise not in ("auto", "off"):
            raise ConfigError(f"identification config: input_denoise must be auto or off, got {self.input_denoise!r}")
        if self.refine_starts not in ("auto", "both", "fallback"):
            raise ConfigError(f"identification config: refine_starts must be auto, both or fallback, "
                              f"got {self.refine_starts!r}")
        if self.power_terms not in ("physics", "any"):
            raise ConfigError(f"identification config: power_terms must be physics or any, got {self.power_terms!r}")
        if self.filter_terms not in ("physics", "any"):
            raise ConfigError(f"identification config: filter_terms must be physics or any, got {self.filter_terms!r}")
        if self.refine_stability_points not in ("records", "smallsignal"):
            raise ConfigError(f"identification config: refine_stability_points must be records or smallsignal, "
                              f"got {self.refine_stability_points!r}")
        if self.lr_schedule not in ("cosine", "onecycle"):
            raise ConfigError(f"identification config: lr_schedule must be cosine or onecycle, got {self.lr_schedule!r}")
        if self.solver not in ("rk4", "euler", "midpoint", "dopri5"):
            raise ConfigError(f"identification config: solver must be rk4, euler, midpoint or dopri5, "
                              f"got {self.solver!r}")

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["roles"] = self.roles.to_dict()
        out["hidden"] = list(self.hidden)
        out["refine_prune_budgets"] = list(self.refine_prune_budgets)
        out["refit_budgets"] = list(self.refit_budgets)
        for key in ("refine_growing_windows", "refine_growing_windows_low_snr", "refine_growing_evaluations",
                    "refine_growing_evaluations_low_snr",
                    "refine_growing_max_windows", "refine_polish_windows", "refine_polish_evaluations",
                    "selection_equilibrium_grid"):
            out[key] = list(getattr(self, key))
        return out
