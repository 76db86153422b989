"""Benchmark of the gap workflow: hidden effects in virtual-HIL data, named or not, how well, how fast.

    python bench/gap_bench.py [--quick] [--out bench/gap_results.json] [--markdown bench/GAP_RESULTS.md]

For every case the virtual HIL generates data with an effect hidden (the reference
is the nameplate plant without effects), clean and at 40 dB SNR; the workflow must
name the effect, fit its main parameter within 10 % and shrink the gap. Prints one
line per case and writes the results JSON and markdown (``--quick``, a subset of the cases: by
default bench/gap_results_quick.json and bench/GAP_RESULTS_quick.md, so that the full matrix's
files stay as they are).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from pisml_ros.gap import GapWorkflow, PlantReference, gap_percent
from pisml_ros.plant import InverterPlant
from pisml_ros.plant.noise import add_measurement_noise
from pisml_ros.plant.scenarios import generate, schedules_for

# (hidden effects, scenario, expected label, main key, true value)
CASES = [
    ({"current_limit": {"imax": 1.5}}, "test", "current_limit", "imax", 1.5),
    ({"current_limit": {"imax": 2.5, "kaw": 30.0}}, "test", "current_limit", "imax", 2.5),
    ({"current_clamp": {"imax_d": 1.0, "imax_q": 1.5}}, "test", "current_clamp", "imax_d", 1.0),
    ({"current_clamp": {"imax_d": 2.0, "imax_q": 2.0}}, "test", "current_clamp", "imax_d", 2.0),
    ({"voltage_limit": {"vmax": 1.2}}, "test", "voltage_limit", "vmax", 1.2),
    ({"voltage_limit": {"vmax": 1.1}}, "test", "voltage_limit", "vmax", 1.1),
    ({"delay": {"td": 1.0e-4}}, "train", "delay", "td", 1.0e-4),
    ({"delay": {"td": 3.0e-4}}, "train", "delay", "td", 3.0e-4),
    ({"virtual_impedance": {"r": 0.02, "x": 0.1}}, "train", "virtual_impedance", "x", 0.1),
    ({"virtual_impedance": {"r": 0.0, "x": 0.05}}, "train", "virtual_impedance", "x", 0.05),
    ({"param_drift": {"Lf": 0.12}}, "train", "param_drift.Lf", "value", 0.12),
    ({"param_drift": {"Cf": 0.04}}, "train", "param_drift.Cf", "value", 0.04),
    ({"param_drift": {"Lg": 0.065}}, "train", "param_drift.Lg", "value", 0.065),
    ({"param_drift": {"Rd": 0.1}}, "train", "param_drift.Rd", "value", 0.1),
    ({"gain_mismatch": {"KpC": 0.3}}, "train", "gain_mismatch.KpC", "value", 0.3),
    ({"gain_mismatch": {"KiV": 4.0}}, "train", "gain_mismatch.KiV", "value", 4.0),
    ({"gain_mismatch": {"mp": 0.04}}, "train", "gain_mismatch.mp", "value", 0.04),
    ({"frequency_limit": {"dw_max": 0.002}}, "train", "frequency_limit", "dw_max", 0.002),
    ({}, "train", None, None, None),
    ({"current_limit": {"imax": 1.5}, "param_drift": {"Lg": 0.06}}, "test", "current_limit+param_drift.Lg", None,
     None),
]
QUICK = [0, 4, 6, 10, 14, 17, 18, 19]


def run_case(effects, scenario, snr, seed=1):
    schedules, duration = schedules_for(scenario, seed=seed)
    clean = generate(InverterPlant(effects=effects), schedules, duration)
    data = add_measurement_noise(clean, snr, seed=seed + 7) if snr else clean
    started = time.monotonic()
    flow = GapWorkflow(PlantReference())
    report = flow.run(data)
    seconds = time.monotonic() - started
    rows = [(k, slice(None)) for k in sorted({w["traj_index"] for w in flow.windows})]
    shrink = None
    if rows:
        before, after = gap_percent(data, flow.preds_before, rows), gap_percent(data, flow.preds_after, rows)
        floor = gap_percent(data, [tr.x for tr in clean], rows)
        shrink = {"before": before, "after": after, "noise_floor": floor}
    return report, seconds, shrink


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a subset of the cases")
    parser.add_argument("--out", help="results JSON (default: bench/gap_results.json, --quick: "
                                      "bench/gap_results_quick.json)")
    parser.add_argument("--markdown", help="results table (default: bench/GAP_RESULTS.md, --quick: "
                                           "bench/GAP_RESULTS_quick.md)")
    args = parser.parse_args(argv)
    suffix = "_quick" if args.quick else ""
    out = Path(args.out or f"bench/gap_results{suffix}.json")
    markdown = Path(args.markdown or f"bench/GAP_RESULTS{suffix}.md")
    cases = [CASES[k] for k in QUICK] if args.quick else CASES
    results = []
    for effects, scenario, label, key, truth in cases:
        for snr in (None, 40.0):
            report, seconds, shrink = run_case(effects, scenario, snr)
            named = "+".join(e.get("label", e["name"]) for e in report["effects"])
            if label is None:
                ok = not report["effects"]
            elif "+" in label:  # exactly these effects, nothing spurious
                ok = sorted(label.split("+")) == sorted(e.get("label", e["name"]) for e in report["effects"])
            else:  # the right effect first; a second one only if it is a real (joint) improvement
                ok = bool(report["effects"]) and report["effects"][0].get("label") == label
            err = None
            if ok and key is not None:
                err = abs(report["effects"][0]["params"][key] / truth - 1) * 100
            row = {"effects": effects, "scenario": scenario, "snr_db": snr, "expected": label, "named": named,
                   "correct": ok, "param_error_pct": err, "seconds": seconds, "gap": shrink,
                   "gap_before": report["gap_before"]["overall"], "gap_after": report["gap_after"]["overall"]}
            results.append(row)
            print(f"{'OK ' if ok else 'BAD'} {label or 'no effect'} ({'clean' if snr is None else '40 dB'}, "
                  f"{scenario}): named [{named or '-'}]"
                  + (f", main parameter error {err:.2f} %" if err is not None else "")
                  + (f", gap {shrink['before']:.2f} -> {shrink['after']:.3f} % (noise floor {shrink['noise_floor']:.3f} %)"
                     if shrink else "") + f", {seconds:.1f} s", flush=True)
    summary = {
        "cases": len(results), "correct": sum(r["correct"] for r in results),
        "max_param_error_pct": max((r["param_error_pct"] for r in results if r["param_error_pct"] is not None),
                                   default=None),
        "median_seconds": float(np.median([r["seconds"] for r in results])),
        "max_seconds": float(np.max([r["seconds"] for r in results])),
        "machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0], "platform": platform.platform()},
        "command": "python bench/gap_bench.py" + (" --quick" if args.quick else ""),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"summary": summary, "results": results}, indent=2, default=float) + "\n")
    lines = ["# Gap workflow benchmark", "", f"`{summary['command']}` — {summary['correct']}/{summary['cases']} "
             f"cases correct; max main-parameter error {summary['max_param_error_pct']:.2f} %; "
             f"median {summary['median_seconds']:.0f} s, max {summary['max_seconds']:.0f} s per case "
             f"({summary['machine']['cpus']} CPUs).", "",
             "| hidden effect | data | named | main param error | gap in windows before → after (noise floor) | time |",
             "|---|---|---|---|---|---|"]
    for r in results:
        gap = (f"{r['gap']['before']:.2f} → {r['gap']['after']:.3f} % ({r['gap']['noise_floor']:.3f} %)"
               if r["gap"] else "no window")
        err = f"{r['param_error_pct']:.2f} %" if r["param_error_pct"] is not None else "-"
        lines.append(f"| {r['expected'] or 'none'} {json.dumps(r['effects'])} | {r['scenario']}, "
                     f"{'clean' if r['snr_db'] is None else '40 dB'} | {'✔ ' if r['correct'] else '✘ '}"
                     f"{r['named'] or '-'} | {err} | {gap} | {r['seconds']:.0f} s |")
    markdown.parent.mkdir(parents=True, exist_ok=True)
    markdown.write_text("\n".join(lines) + "\n")
    print(f"{summary['correct']}/{summary['cases']} correct; results in {out} and {markdown}")
    return 0 if summary["correct"] == summary["cases"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
