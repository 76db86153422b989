"""Hybrid training on CPU and GPU: the same PISML identification with ``device`` cpu and cuda.

    python bench/gpu_bench.py [--snr 40] [--devices cpu,cuda] [--out bench/gpu_results.json]

Runs PISML on the paper protocol's 12 training trajectories (+ small-signal set) once per device
and prints, per device: the hybrid training time (the only stage that uses the device), the
whole identification time, and the explicit model's IOD/OOD errors against the clean truth.
Nothing else in the pipeline moves to the GPU (backbone, distillation and the refinement stay on
the CPU), so the whole-run time says how much the GPU helps an identification, not only training.
A device torch cannot use is reported as skipped. Writes the figures to the results JSON.
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
    parser.add_argument("--snr", type=float, default=None, help="measurement noise (dB); default clean")
    parser.add_argument("--devices", default="cpu,cuda")
    parser.add_argument("--out", default=str(BENCH / "gpu_results.json"))
    parser.add_argument("--threads", type=int, default=None,
                        help="torch CPU threads (default torch's own: one per core)")
    args = parser.parse_args(argv)

    import torch

    if args.threads is not None:
        torch.set_num_threads(args.threads)

    from bench import PLANTS, datasets  # the identification benchmark's protocol data, same seeds
    from pisml_ros.analysis.metrics import protocol_errors
    from pisml_ros.ident import IdentConfig, make_estimator

    _, train, small, test = datasets(PLANTS["standard"], args.snr)
    runs = {}
    for device in args.devices.split(","):
        if device.startswith("cuda") and not torch.cuda.is_available():
            runs[device] = {"skipped": "torch sees no CUDA GPU"}
            print(f"{device}: skipped (torch sees no CUDA GPU)", flush=True)
            continue
        started = time.monotonic()
        est = make_estimator("pisml", IdentConfig.from_mapping({"device": device})).fit(train, small)
        seconds = time.monotonic() - started
        errors = protocol_errors(est.explicit_model_, test)
        runs[device] = {"hybrid_training_s": round(est.metrics_["hybrid_seconds"], 2),
                        "identification_s": round(seconds, 2),
                        "refinement_s": round(est.metrics_.get("refine_seconds", float("nan")), 2),
                        "iod_pct": round(float(errors["iod"]), 4), "ood_pct": round(float(errors["ood"]), 4),
                        "nonzero": int(est.explicit_model_.n_parameters),
                        "final_trajectory_loss": float(est.metrics_["final_trajectory_loss"])}
        print(f"{device}: {runs[device]}", flush=True)
    result = {"command": "python bench/gpu_bench.py " + " ".join(argv if argv is not None else sys.argv[1:]),
              "date": time.strftime("%Y-%m-%d"), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
              "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
              "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
              "data": "clean" if args.snr is None else f"{args.snr:g} dB", "runs": runs}
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
