"""How the refinement's multiple shooting scales with threads: seconds per cost evaluation.

    python bench/threads_bench.py [--snr 40] [--parts 1,2,4,8] [--model model.json] [--out FILE]

The refinement (most of a noisy-data identification) integrates its shooting windows in parts,
one thread per part (``TrajectoryFitter(threads=...)``). Each part launches many small torch
operations, and between them Python holds the GIL, so the parts contend for it: past a few
threads more parts cost more than they save. This script fits one stage of the growing-window
refinement (windows of 25 samples over all the paper protocol's training data, the small-signal
records and the priors as in a PISML fit) with each number of parts and prints the seconds per
cost evaluation and the final cost (the same up to rounding: the parts only share the work out).

The model refined is ``--model`` (an explicit model JSON), or by default the explicit model that
PISML distils before its refinement (``refine: false``) on the same data. Writes the figures to
the results JSON (default ``bench/threads_results.json``).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
sys.path[:0] = [str(BENCH), str(BENCH.parent)]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--snr", type=float, default=40.0, help="measurement noise (dB); default 40")
    parser.add_argument("--parts", default="1,2,3,4,8", help="comma-separated numbers of parts to time")
    parser.add_argument("--evaluations", type=int, default=6, help="cost evaluations per fit")
    parser.add_argument("--window", type=int, default=25, help="samples per shooting window")
    parser.add_argument("--model", default=None, help="explicit model JSON to refine (default: PISML's distilled model)")
    parser.add_argument("--out", default=str(BENCH / "threads_results.json"))
    args = parser.parse_args(argv)

    import numpy as np
    import torch

    from bench import PLANTS, datasets  # the identification benchmark's protocol data, same seeds
    from pisml_ros.ident import IdentConfig, make_estimator
    from pisml_ros.ident.estimators import _stability_anchors
    from pisml_ros.ident.noise import residual_weights
    from pisml_ros.ident.trajfit import TrajectoryFitter
    from pisml_ros.model import ExplicitModel
    from pisml_ros.model.expressions import term_set

    _, train, small, _ = datasets(PLANTS["standard"], args.snr)
    cfg = IdentConfig()
    if args.model:
        model = ExplicitModel.load(args.model)
    else:
        started = time.monotonic()
        model = make_estimator("pisml", IdentConfig.from_mapping({"refine": False})).fit(train, small).explicit_model_
        print(f"distilled model: {model.n_parameters} coefficients ({time.monotonic() - started:.1f} s)", flush=True)
    signals = tuple(model.state_names) + tuple(model.input_names)
    weights = residual_weights(train)
    coef = np.asarray(model.coefficients, dtype=float)

    runs = {}
    for parts in (int(p) for p in args.parts.split(",")):
        fitter = TrajectoryFitter(term_set(model.terms, signals), model.n_states, train.dt, window=args.window,
                                  weights=weights, threads=parts)
        started = time.monotonic()
        result = fitter.fit(coef, coef != 0, train, small, lambda_jac=1.0, max_nfev=args.evaluations,
                            fit_starts_first=True, lambda_stab=cfg.refine_growing_stability_weight,
                            stability_margin=cfg.refine_stability_margin,
                            stability_records=_stability_anchors(train, small, cfg),
                            lambda_eq=cfg.refine_equilibrium_weight, ftol=0.0)
        seconds = time.monotonic() - started
        runs[str(parts)] = {"seconds": round(seconds, 3), "evaluations": int(result.nfev),
                            "seconds_per_evaluation": round(seconds / max(result.nfev, 1), 4),
                            "final_cost": float(result.cost)}
        print(f"parts {parts}: {runs[str(parts)]}", flush=True)
    result = {"command": "python bench/threads_bench.py " + " ".join(argv if argv is not None else sys.argv[1:]),
              "date": time.strftime("%Y-%m-%d"), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
              "python": platform.python_version(), "torch": torch.__version__,
              "data": f"{args.snr:g} dB", "window": args.window, "coefficients": int(model.n_parameters),
              "runs": runs}
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
