"""How much better held input levels would help: an oracle for noisy measured inputs.

With 40 dB on the states and on the inputs (ug, theta_g), each stretch where the clean input is
constant (the exact change points) is held at the truth plus ``alpha`` times the error of the noisy
samples' mean there: alpha = 1 is the stretch mean (what the engine's holding reaches at best),
0 the exact inputs. PISML (default settings) is fitted on each and scored on the protocol's test
records. Measured at stop 50 (README, "Noise on the measured inputs"):

    .venv/bin/python bench/input_level_oracle.py 0 0.5,0.25
"""
import json
import sys
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent
sys.path[:0] = [str(BENCH), str(BENCH.parent)]


def held(noisy, exact, alpha):
    """``noisy`` with each input held, on the stretches where ``exact`` is constant, at the exact
    level plus ``alpha`` times the noisy mean's error there."""
    from pisml_ros.data import Dataset, Trajectory

    out = []
    for tn, te in zip(noisy, exact):
        u = np.array(te.u, dtype=float)
        for j in range(u.shape[1]):
            col = te.u[:, j]
            edges = np.flatnonzero(np.diff(col) != 0) + 1
            for a, b in zip([0, *edges], [*edges, len(col)]):
                u[a:b, j] = col[a] + alpha * (tn.u[a:b, j].mean() - col[a])
        out.append(Trajectory(tn.traj_id, tn.t, tn.x, u))
    return Dataset(noisy.state_names, noisy.input_names, out, dict(noisy.metadata))


def main(argv=None) -> int:
    from bench import datasets, make_estimator

    from pisml_ros.analysis.metrics import protocol_errors
    from pisml_ros.ident import IdentConfig

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print(__doc__)
        return 2
    seed, alphas = int(args[0]), [float(a) for a in args[1].split(",")]
    _, train, small, test = datasets(None, 40, seed=seed, input_noise=True)
    _, train_exact, small_exact, _ = datasets(None, None, seed=seed)
    for alpha in alphas:
        started = time.monotonic()
        est = make_estimator("pisml", IdentConfig.load(None, {})).fit(held(train, train_exact, alpha),
                                                                      held(small, small_exact, alpha))
        print(json.dumps({"seed": seed, "alpha": alpha, "errors": protocol_errors(est.model_, test),
                          "coefficients": int(est.explicit_model_.n_parameters),
                          "seconds": round(time.monotonic() - started, 1)}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
