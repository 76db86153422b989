"""Which stages of a fit lose by the held inputs: exact training inputs given to some stages only.

With 40 dB on the measured inputs too (the "noisy inputs" scenario), the engine holds ug and theta_g
at their stretch means (:func:`pisml_ros.ident.noise.piecewise_constant_inputs`), each level off by
σ/√n. This script fits PISML (default settings) on one recording per seed with the training records'
inputs exact in some stages, the small-signal records' held (but in the last two modes), and scores the model on the
protocol's test records:

- ``held``: the engine as it is (every stage on the held inputs);
- ``exact``: the training records' exact inputs everywhere (nothing held there);
- ``late``: held inputs up to the distillation, exact ones in the trajectory refinement and in every
  free-run training score (the selection's and the refinement's own checks);
- ``early``: exact inputs up to the distillation, held ones in the refinement and the scores;
- ``smallsignal``: the small-signal records' exact inputs, the training records' held;
- ``both``: every record's exact inputs (the same records' states, their noise as drawn with the
  inputs' noise: the control of how these recordings fare without any).

``late`` and ``early`` swap the records the estimator passes to ``refine_explicit`` and
``training_errors`` (patched in :mod:`pisml_ros.ident.estimators` for the fit's duration): a
diagnostic, not an engine setting. Stop 93 (README, "Stop 93"):

    .venv/bin/python bench/input_stages.py --modes late --seeds 280-287 --out late.json
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import sys
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
sys.path[:0] = [str(BENCH), str(BENCH.parent)]

MODES = ("held", "exact", "late", "early", "smallsignal", "both")


@contextlib.contextmanager
def records_swapped(replacements: dict):
    """Within the block, the estimator's refinement and free-run scores see ``replacements[len(d)]``
    for a dataset ``d`` of that many records (the training records, or the training and small-signal
    records its scores run on), ``d`` itself otherwise."""
    from pisml_ros.ident import estimators

    refine, errors = estimators.refine_explicit, estimators.training_errors

    def swapped(dataset):
        return replacements.get(len(dataset), dataset)

    def refine_swapped(model, train, smallsignal, cfg, *args, **kwargs):
        if kwargs.get("scoring") is not None:
            kwargs["scoring"] = swapped(kwargs["scoring"])
        return refine(model, swapped(train), smallsignal, cfg, *args, **kwargs)

    estimators.refine_explicit = refine_swapped
    estimators.training_errors = lambda models, train, known=None: errors(models, swapped(train), known)
    try:
        yield
    finally:
        estimators.refine_explicit, estimators.training_errors = refine, errors


def fit_mode(mode: str, seed: int) -> dict:
    """One fit of the noisy-input recording ``seed`` with the inputs of ``mode``; its test errors, the
    ug (0.2-1.1) where it has an unstable mode and the plant none, coefficients, chosen candidate and
    wall time."""
    from bench import datasets, make_estimator, plant_grid, spectra, spurious_points

    from pisml_ros.analysis.metrics import protocol_errors
    from pisml_ros.data import Dataset
    from pisml_ros.data.dataset import concat_datasets
    from pisml_ros.ident import IdentConfig
    from pisml_ros.ident.noise import input_noise_std, piecewise_constant_inputs

    plant, train, small, test = datasets({}, 40.0, seed=seed, input_noise=True)
    _, clean, clean_small, _ = datasets({}, None, seed=seed)

    def exact_inputs(noisy, clean):
        return Dataset(noisy.state_names, noisy.input_names,
                       [dataclasses.replace(tr, u=c.u.copy()) for tr, c in zip(noisy, clean)],
                       {k: v for k, v in noisy.metadata.items() if k != "inputs_denoised"})

    exact = exact_inputs(train, clean)
    given = exact if mode in ("exact", "early", "both") else train
    if mode in ("smallsignal", "both"):
        small = exact_inputs(small, clean_small)
    swapping = contextlib.nullcontext()
    if mode in ("late", "early"):
        # the held records as the estimator's own start makes them (the same function and noise estimate)
        late = exact if mode == "late" else piecewise_constant_inputs(train, sigma=input_noise_std(train))[0]
        held_small, _ = piecewise_constant_inputs(small, sigma=input_noise_std(small))
        swapping = records_swapped({len(train): late, len(train) + len(small): concat_datasets([late, held_small])})
    started = time.monotonic()
    with swapping:
        est = make_estimator("pisml", IdentConfig()).fit(given, small)
    errors = protocol_errors(est.model_, test)
    grid = plant_grid(plant)
    spurious = spurious_points(spectra(est.model_, grid), {g: plant.eigenvalues(g, 0.0) for g in grid})
    return {"seed": seed, "mode": mode, "iod": errors["iod"], "ood": errors["ood"], "spurious": spurious,
            "coefficients": int(est.model_.n_parameters), "chosen": est.model_.metadata["selection"]["chosen"],
            "seconds": round(time.monotonic() - started, 1)}


def seeds_of(text: str) -> list:
    """``"280-283,290"`` -> [280, 281, 282, 283, 290]."""
    out = []
    for part in text.split(","):
        first, _, last = part.strip().partition("-")
        out.extend(range(int(first), int(last or first) + 1))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--modes", default=",".join(MODES), help=f"comma-separated, of {', '.join(MODES)}")
    parser.add_argument("--seeds", default="280-287", help="noisy-input recordings, e.g. 280-287 or 244,246")
    parser.add_argument("--out", help="JSON file for the rows")
    args = parser.parse_args(argv)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        parser.error(f"--modes: unknown {unknown} (known: {', '.join(MODES)})")
    rows = []
    for seed in seeds_of(args.seeds):
        for mode in modes:
            row = fit_mode(mode, seed)
            rows.append(row)
            print(f"{seed} {mode:5s} IOD {row['iod']:.3f} OOD {row['ood']:.3f} spurious {row['spurious']} "
                  f"n {row['coefficients']} "
                  f"{row['chosen']} {row['seconds']:.0f} s", flush=True)
            if args.out:  # after every fit: a long run stopped early keeps what it measured
                Path(args.out).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
