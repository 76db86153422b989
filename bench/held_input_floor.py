"""What the engine's held inputs cost the plant itself: the true plant's free run on noisy inputs.

With 40 dB on the measured inputs (scenario "noisy inputs"), the engine holds each input at its
mean where it is constant (``ident.noise.piecewise_constant_inputs``). This script runs the *true*
plant (exact structure and parameters, started at its exact rest states) on the training and
small-signal records with the inputs (a) exact, (b) held as the engine holds them, (c) as measured,
and scores each run against the noisy records with the selection's own training error
(``analysis.metrics.relative_error`` averaged over the records, %, beside
``ident.noise.noise_floor_error``), and against the clean records. What a fit's candidates score
(``selection.training_error_pct`` in a sweep's rows) can then be read against what the truth
scores on the same inputs. Stop 90::

    .venv/bin/python bench/held_input_floor.py --seeds 240-247
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent
sys.path[:0] = [str(BENCH), str(BENCH.parent)]


def true_runs(seed: int, snr: float) -> dict:
    """For one recording: the true plant's training error (%) on its noisy scoring records with
    exact, held and measured inputs, against the noisy and the clean records, and the noise floor."""
    from bench import datasets

    from pisml_ros.analysis.metrics import relative_error
    from pisml_ros.data import Dataset
    from pisml_ros.ident.noise import noise_floor_error, piecewise_constant_inputs
    from pisml_ros.plant.scenarios import simulate

    plant, train, small, _ = datasets({}, snr, seed=seed, input_noise=True)
    _, clean_train, clean_small, _ = datasets({}, None, seed=seed)
    # each record started at the plant's rest for its schedule (the generator keeps the schedules)
    schedules = train.metadata["schedules"] + small.metadata["schedules"]
    starts = [plant.equilibrium(s["ug0"], s["theta0"]) for s in schedules]
    noisy = list(train) + list(small)
    clean = list(clean_train) + list(clean_small)
    held = list(piecewise_constant_inputs(train)[0]) + list(piecewise_constant_inputs(small)[0])
    dt = train.metadata["dt"]
    n_measured = len(plant.state_names)
    out = {"seed": seed, "noise_floor_pct": noise_floor_error(Dataset(train.state_names, train.input_names, noisy, {}))}
    for label, inputs in (("exact", clean), ("held", held), ("measured", noisy)):
        runs = [simulate(plant, x0[None], tr.u[None], dt)[0, :, :n_measured] for x0, tr in zip(starts, inputs)]
        out[label] = {"against_noisy_pct": float(np.mean([relative_error(x, tr.x) for x, tr in zip(runs, noisy)])),
                      "against_clean_pct": float(np.mean([relative_error(x, tr.x) for x, tr in zip(runs, clean)]))}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="240-247", help="recordings, e.g. 240-247 or 0-3,7")
    parser.add_argument("--noise", type=float, default=40.0, help="SNR in dB, on the states and the inputs")
    parser.add_argument("--out", default=None, help="JSON file for the figures (default: none)")
    args = parser.parse_args(argv)
    from setting_sweep import parse_seeds

    rows = []
    for seed in parse_seeds(args.seeds):
        row = true_runs(seed, args.noise)
        rows.append(row)
        print(f"seed {seed}: noise floor {row['noise_floor_pct']:.3f} %; the true plant against the noisy records "
              + ", ".join(f"{k} inputs {row[k]['against_noisy_pct']:.3f} %" for k in ("exact", "held", "measured"))
              + "; against the clean records "
              + ", ".join(f"{k} {row[k]['against_clean_pct']:.3f} %" for k in ("exact", "held", "measured")),
              flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps({"noise_db": args.noise, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
