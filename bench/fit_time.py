"""Where one PISML fit's time goes: the estimator's stage clocks and every trajectory-fit stage of
its refinements, from the fit's own records (``metrics_`` and each candidate's metadata).

The issue's speed target is a median over fits (<= 60 s on 2 cores); this is the tool for finding
what a fit spends it on. Per refinement family (a start, the rescue, a fallback) it prints the
growing-window stages (``metadata["refinement"]["stages"]``) and each prune round's polish
(``metadata["pruning"]["polish_stages"]``): window, support, cost evaluations, accepted steps (each
one Gauss-Newton pass, the expensive part, and a stage takes one more at its start), wall seconds
and the cost reached. Stages of two families that ran side by side overlap in time; the process's
CPU time over the fit's wall time says how busy the cores were.

    .venv/bin/python bench/fit_time.py [--scenario protocol] [--plant standard] [--seed 1] \
        [--noise 40] [--set KEY=VALUE ...] [--out fit_time.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
sys.path[:0] = [str(BENCH), str(BENCH.parent)]


def family_stages(candidates: dict) -> dict:
    """``{family: [stage record, ...]}`` from the candidates' metadata: a family is a refinement's
    candidates (``"refined"`` and its prune rounds, with the same name suffix); its stages are the
    growing-window stages, then each round's polish, in the order they ran."""
    from pisml_ros.ident.selection import _refinement_family

    families: dict = {}
    for name, model in candidates.items():
        suffix = _refinement_family(name)  # the engine's own reading of its candidate names
        if suffix is None:
            continue
        meta = getattr(model, "metadata", {}) or {}
        refinement, pruning = meta.get("refinement") or {}, meta.get("pruning") or {}
        if name.startswith("refined") and refinement.get("stages"):
            families.setdefault(suffix.strip(), {})[0] = [dict(stage, part="growing") for stage in refinement["stages"]]
        elif pruning.get("polish_stages"):
            families.setdefault(suffix.strip(), {})[pruning["round"]] = [
                dict(stage, part=f"polish {pruning['round']}") for stage in pruning["polish_stages"]]
    return {suffix or "first start": [s for _, stages in sorted(parts.items()) for s in stages]
            for suffix, parts in families.items()}


def format_stage(stage: dict) -> str:
    # (the windows' count since stop 67)
    windows = f" x {stage['windows']:3d}" if stage.get("windows") is not None else ""
    return (f"  {stage['part']:10s} window {stage['window']:4d}{windows}  support {stage['support']:4d}  "
            f"evaluations {stage['evaluations']:3d}  accepted {stage['accepted']:3d}  {stage['seconds']:6.2f} s  "
            f"cost {stage['cost']:.6g}")


def extra_runs(meta: dict) -> list[str]:
    """Why the fit ran more than its two starts, from the chosen model's metadata: the rescue's and
    the unrestricted fallback's records (their trigger: the score of the model the selection would
    have taken over the noise floor, and its rest points it is inconsistent with)."""
    lines = []
    for key, label in (("refinement_rescue", "rescue"), ("refinement_unrestricted", "unrestricted fallback")):
        record = meta.get(key)
        if not record:
            continue
        ratio = record.get("ratio")
        ran = "ran" if record.get("run") else "superseded by the limit" if record.get("superseded_by_limit") \
            else "not run"
        lines.append(f"{label}: {ran} (before it: {record.get('selected_before')!r}, "
                     f"{'' if ratio is None else f'{ratio:.2f}x the noise floor, '}"
                     f"inconsistent at {record.get('inconsistent_rest_points', 0)} rest points"
                     f"{', refinement lost' if record.get('refinement_lost') else ''})")
    return lines


def main(argv=None) -> int:
    from scenarios_bench import add_recording_options, recording_from_options

    from pisml_ros.ident import IdentConfig, make_estimator

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_recording_options(parser, seed=1)
    parser.add_argument("--out", help="JSON file for the clocks and the stage records")
    args = parser.parse_args(argv)
    _, train, small, _, settings = recording_from_options(args, parser)
    wall, cpu = time.monotonic(), time.process_time()
    est = make_estimator("pisml", IdentConfig.load(None, settings)).fit(train, small)
    wall, cpu = time.monotonic() - wall, time.process_time() - cpu
    clocks = {key: round(value, 2) for key, value in est.metrics_.items() if key.endswith("seconds")}
    print(f"{args.scenario} recording {args.seed}, {args.noise} dB, {args.plant} plant: {wall:.1f} s wall, "
          f"{cpu:.1f} s CPU (cores {cpu / wall:.2f} busy on average); chosen "
          f"{est.model_.metadata['selection']['chosen']!r}")
    print("stage clocks (s): " + ", ".join(f"{key.removesuffix('_seconds')} {value}" for key, value in clocks.items()))
    for line in extra_runs(est.model_.metadata):
        print(line)
    families = family_stages(est.candidates_)
    for family, stages in families.items():
        total = sum(stage["seconds"] for stage in stages)
        passes = sum(stage["accepted"] + 1 for stage in stages)  # a stage's first pass is at its start
        print(f"{family}: {total:.1f} s in {len(stages)} stages, {passes} Gauss-Newton passes "
              f"({sum(stage['evaluations'] for stage in stages)} cost evaluations)")
        for stage in stages:
            print(format_stage(stage))
    if args.out:
        Path(args.out).write_text(json.dumps({"scenario": args.scenario, "plant": args.plant, "seed": args.seed,
                                              "noise": args.noise, "settings": settings, "wall_seconds": wall,
                                              "cpu_seconds": cpu, "clocks": clocks, "families": families},
                                             indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
