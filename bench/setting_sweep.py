"""Measure an identification setting over many recordings and compare it with another, row by row.

Every engine option in ``pisml_ros/ident/config.py`` was measured on a handful of 40 dB recordings
with scratch scripts that were lost with each machine, so every stop re-measured the default first.
This keeps the per-recording rows in the repository (``bench/sweeps/*.json``): the chosen model's
IOD / OOD error on the protocol's test records, its spectrum at ug 0.8 against the plant's, spurious
unstable modes over ug 0.2-1.1, its size, and the fit's time. A change is then compared with the
same recordings' rows, and the summary counts what the issue's 40 dB targets ask of each
recording (IOD <= 0.5 %, OOD <= 1.0 %, no spurious unstable mode, compression >= 250x). Where the
recordings come from the default plant, each row also keeps the chosen model's stability verdicts
in the 3-bus microgrid and behind a weak line (``bench/microgrid_bench.py``'s, at 1.0 p.u.; ~1 s),
which the records alone do not pin.

    .venv/bin/python bench/setting_sweep.py run --name ridge-1e-4 --set refine_ridge_weight=0.0001 \\
        [--seeds 0-15] [--scenario protocol] [--noise 40]      # ~1-1.5 min a recording on 2 cores
    .venv/bin/python bench/setting_sweep.py compare bench/sweeps/default.json bench/sweeps/ridge-1e-4.json
    .venv/bin/python bench/setting_sweep.py import --name NAME FILE...   # bench/candidates.py --out files

``run`` writes ``bench/sweeps/NAME.json`` after every recording and skips the recordings already
in it, so an interrupted sweep goes on where it stopped. Recordings 0-9 of the protocol are
``make bench``'s ten 40 dB recordings; the engine was tuned on those, not on 10-15.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent
sys.path[:0] = [str(BENCH), str(BENCH.parent)]
SWEEPS = BENCH / "sweeps"

# the 40 dB targets for one recording
IOD_TARGET, OOD_TARGET, COMPRESSION_TARGET = 0.5, 1.0, 250.0
# the default hybrid (the paper's MLP, 20 749 parameters, plus a backbone of ~300) over 250: what
# a row without the hybrid's count (an imported one) is held to
COEFFICIENTS_FOR_TARGET = 84
# a chosen model's equilibrium further than this from the plant's in reactive power (p.u., worst over
# bench.OPERATING_POINT_GRID), or none there, counts as an operating point gone wrong. Stop 60: the
# target counts alone did not see it; filter_terms physics, ahead on them, had 1.5 and 2.6e3 p.u. on
# two of the ten benchmark recordings and wrong microgrid verdicts there, where any's worst is 0.24
# (on the unseen recordings 10-23, though, any had 3 of 14 above 0.3 and physics 1)
OPERATING_POINT_DQ_LIMIT = 0.3
# the selection's record kept in each row beside the chosen name (every candidate's training error,
# its inconsistent rest points, the hold's error and the noise floor)
SELECTION_KEYS = ("training_error_pct", "inconsistent_rest_points", "hold_error_pct", "noise_floor_pct")


def parse_seeds(text: str) -> list[int]:
    """``"0-3,7"`` -> ``[0, 1, 2, 3, 7]``."""
    seeds: list[int] = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        low, sep, high = part.partition("-")
        try:
            seeds += list(range(int(low), int(high) + 1)) if sep else [int(low)]
        except ValueError:
            raise ValueError(f"--seeds {text!r}: expected numbers and ranges such as 0-15,20") from None
    return sorted(set(seeds))


def microgrid_right(row: dict) -> bool | None:
    """Whether the row's model gets the default plant's stability verdicts right (stable in the 3-bus
    microgrid with the grid at 1.0 p.u., and behind every weak line of the sweep at 1.0 p.u., as the
    plant is); None where not measured (rows from before stop 62, or another plant's recordings)."""
    if "mg_max_real" not in row:
        return None
    return not any(wrong_verdict(own) for own, _ in microgrid_points(row))


def wrong_verdict(own) -> bool:
    """Whether a largest real part (None: no operating point) is the wrong verdict where the plant is stable."""
    return own is None or own >= 0


def microgrid_points(row: dict) -> list:
    """``(own, alternatives)`` largest real parts at each point of the row's microgrid verdicts (the
    3-bus microgrid, then each weak line): the chosen model's, and its alternatives' (the fit's
    candidates that reproduced the records about as well; ``[]`` in rows from before they were kept)."""
    weak = row.get("weak_max_real") or []
    others = [row.get("mg_alternatives") or []] + list(row.get("weak_alternatives") or [[]] * len(weak))
    return list(zip([row.get("mg_max_real")] + list(weak), others))


def flagged(own, alternatives) -> bool:
    """Whether a model's alternatives leave its verdict at one point open: one of them gives the
    other sign, or has no operating point where the model has one (or the reverse)."""
    from pisml_ros.analysis.operating_point import verdict_differs

    return any(verdict_differs(own, alt) for alt in alternatives)


def meets(row: dict) -> dict:
    """Which of the issue's 40 dB targets one recording's row meets (``None``: not measured)."""
    finite = row.get("iod") is not None and row.get("ood") is not None
    accuracy = finite and row["iod"] <= IOD_TARGET and row["ood"] <= OOD_TARGET
    if row.get("hybrid_parameters"):
        compressed = row["hybrid_parameters"] / row["coefficients"] >= COMPRESSION_TARGET
    else:
        compressed = row["coefficients"] <= COEFFICIENTS_FOR_TARGET
    out = {"accuracy": bool(accuracy), "no_spurious": not row.get("spurious"),
           "compression": bool(compressed), "all": bool(accuracy and not row.get("spurious") and compressed)}
    # rows from before stop 60 did not measure the operating point: None (not measured) there
    out["operating_point"] = None if "op_dq" not in row else (
        row["op_dq"] is not None and row["op_dq"] <= OPERATING_POINT_DQ_LIMIT)
    out["microgrid"] = microgrid_right(row)
    # where the verdicts are measured: whether the alternatives flag every wrong one as open (the
    # analysis then says the records do not decide), and whether they flag a right one (a false alarm)
    points = microgrid_points(row) if out["microgrid"] is not None else []
    wrong = [(own, others) for own, others in points if wrong_verdict(own)]
    out["microgrid_wrong_flagged"] = bool(wrong) and all(flagged(own, others) for own, others in wrong)
    out["microgrid_false_alarm"] = any(flagged(own, others) for own, others in points if not wrong_verdict(own))
    return out


def summary(rows: list[dict]) -> dict:
    """Counts of recordings meeting each target, and the spread of the errors and sizes."""
    verdicts = [meets(r) for r in rows]
    iod = [r["iod"] if r.get("iod") is not None else np.inf for r in rows]
    ood = [r["ood"] if r.get("ood") is not None else np.inf for r in rows]
    out = {"recordings": len(rows),
           "accuracy_and_no_spurious": sum(v["accuracy"] and v["no_spurious"] for v in verdicts),
           "spurious": sum(not v["no_spurious"] for v in verdicts),
           "compression": sum(v["compression"] for v in verdicts),
           "all_targets": sum(v["all"] for v in verdicts),
           "operating_point_wrong": sum(v["operating_point"] is False for v in verdicts),
           "operating_point_measured": sum(v["operating_point"] is not None for v in verdicts),
           "microgrid_wrong": sum(v["microgrid"] is False for v in verdicts),
           "microgrid_measured": sum(v["microgrid"] is not None for v in verdicts),
           "microgrid_wrong_flagged": sum(v["microgrid_wrong_flagged"] for v in verdicts),
           "microgrid_false_alarms": sum(v["microgrid_false_alarm"] for v in verdicts)}
    # the same over every verdict point (the 3-bus microgrid and each weak line of every row)
    points = [(own, others) for r in rows if microgrid_right(r) is not None for own, others in microgrid_points(r)]
    wrong = [(own, others) for own, others in points if wrong_verdict(own)]
    out.update(microgrid_points=len(points), microgrid_points_wrong=len(wrong),
               microgrid_points_wrong_flagged=sum(flagged(own, others) for own, others in wrong),
               microgrid_points_right_flagged=sum(flagged(own, others) for own, others in points
                                                  if not wrong_verdict(own)))
    if rows:
        out.update(iod_median=float(np.median(iod)), iod_worst=float(np.max(iod)),
                   ood_median=float(np.median(ood)), ood_worst=float(np.max(ood)),
                   coefficients_median=float(np.median([r["coefficients"] for r in rows])))
        times = [r["seconds"] for r in rows if r.get("seconds") is not None]
        if times:
            out.update(seconds_median=float(np.median(times)), seconds_worst=float(np.max(times)))
        cpu = [r["cpu_seconds"] for r in rows if r.get("cpu_seconds") is not None]
        if cpu:
            out.update(cpu_seconds_median=float(np.median(cpu)))
    return out


def load(path: Path) -> dict:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise SystemExit(f"setting_sweep: cannot read {path}: {err}") from None
    if not isinstance(data.get("rows"), dict):
        raise SystemExit(f"setting_sweep: {path}: no 'rows' (not a sweep file)")
    return data


def save(path: Path, data: dict) -> None:
    ordered = dict(sorted(data["rows"].items(), key=lambda kv: int(kv[0])))
    data = {**data, "rows": ordered, "summary": summary(list(ordered.values()))}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)  # a sweep interrupted mid-write keeps its last complete file


def scored_row(model, plant, test, grid, truth) -> dict:
    """The chosen model's figures on the protocol's test records (as ``make bench`` scores them),
    and its operating point's worst errors in P and Q against the plant's (``op_dp``, ``op_dq``;
    None where it has no equilibrium at a point of ``bench.OPERATING_POINT_GRID``)."""
    from bench import finite, operating_point_errors, spectra, spurious_points

    from pisml_ros.analysis.metrics import protocol_errors, spectrum_wasserstein

    try:
        errors = protocol_errors(model, test)
    except Exception:  # a model that cannot be simulated is a result here
        errors = {"iod": float("nan"), "ood": float("nan")}
    found = spectra(model, grid)
    w = spectrum_wasserstein(found[0.8], truth[0.8]) if found.get(0.8) is not None else float("nan")
    op = operating_point_errors(model, plant)
    return {"iod": finite(errors["iod"]), "ood": finite(errors["ood"]), "w_ug08": finite(w),
            "spurious": spurious_points(found, truth), "coefficients": int(model.n_parameters),
            "op_dp": op["dp"], "op_dq": op["dq"]}


def run(args) -> int:
    from bench import make_estimator, plant_grid, settings_or_exit
    from scenarios_bench import SCENARIOS, scenario_datasets

    from microgrid_bench import quick_verdicts

    from pisml_ros.ident import IdentConfig
    from pisml_ros.plant import PlantParameters

    if args.scenario not in SCENARIOS:
        raise SystemExit(f"setting_sweep: --scenario {args.scenario!r}: not one of {sorted(SCENARIOS)}")
    settings = settings_or_exit(args.set)
    config = IdentConfig.load(None, settings)
    snr = None if args.noise == "clean" else float(args.noise)
    path = Path(args.out) if args.out else SWEEPS / f"{args.name}.json"
    data = load(path) if path.exists() else {"name": args.name, "rows": {}}
    header = {"scenario": args.scenario, "noise": args.noise, "settings": settings}
    if data.get("settings") is not None and {k: data.get(k) for k in header} != header:
        raise SystemExit(f"setting_sweep: {path} holds another sweep ({ {k: data.get(k) for k in header} }); "
                         f"give another --name or --out")
    data.update(header)
    for seed in parse_seeds(args.seeds):
        if str(seed) in data["rows"]:
            continue
        plant, train, small, test = scenario_datasets(SCENARIOS[args.scenario], snr, seed)
        grid = plant_grid(plant)
        # the microgrid and weak-grid configurations are built around the default plant
        default_plant = plant.params == PlantParameters() and not plant.effects
        truth = {g: plant.eigenvalues(g, 0.0) for g in grid}
        started, cpu_started = time.monotonic(), time.process_time()
        est = make_estimator("pisml", config).fit(train, small)
        seconds, cpu_seconds = time.monotonic() - started, time.process_time() - cpu_started
        row = scored_row(est.model_, plant, test, grid, truth)
        if default_plant:
            verdicts = quick_verdicts(est.model_)
            row.update(mg_max_real=verdicts["grid_tied_max_real"], weak_max_real=verdicts["weak_max_real"],
                       mg_alternatives=verdicts["grid_tied_alternatives"],
                       weak_alternatives=verdicts["weak_alternatives"])
        if args.models:
            Path(args.models).mkdir(parents=True, exist_ok=True)
            est.model_.save(Path(args.models) / f"{args.name}_{seed}.json")
        selection = est.model_.metadata.get("selection", {})
        # the CPU time too: the same fit's wall time moved by 40 % with the machine's state within an
        # hour (stop 67), and its CPU time with it, so a time compares only with one measured alongside
        row.update(chosen=selection.get("chosen"), seconds=round(seconds, 1), cpu_seconds=round(cpu_seconds, 1),
                   hybrid_parameters=int(est.metrics_.get("hybrid_parameters") or 0) or None,
                   # what the selection saw, so that a change of the rule (or a choice between two
                   # settings' candidates) can be replayed on the rows without fitting again
                   selection={key: selection.get(key) for key in SELECTION_KEYS})
        data["rows"][str(seed)] = row
        save(path, data)
        print(f"seed {seed}: {format_row(row)}", flush=True)
    print(format_summary(load(path)))
    return 0


def import_tables(args) -> int:
    """Rows from ``bench/candidates.py --out`` files (their chosen candidate), as ``run`` writes them."""
    path = Path(args.out) if args.out else SWEEPS / f"{args.name}.json"
    data = {"name": args.name, "rows": {}, "imported_from": "bench/candidates.py"}
    for name in args.files:
        table = load(Path(name))
        if "chosen" not in table or table["chosen"] not in table["rows"]:
            raise SystemExit(f"setting_sweep: {name}: no chosen candidate (not a bench/candidates.py file)")
        header = {"scenario": table["scenario"], "noise": table["noise"], "settings": table.get("settings", {})}
        if data.get("settings") is not None and {k: data.get(k) for k in header} != header:
            raise SystemExit(f"setting_sweep: {name}: another scenario, noise or setting than the files before it")
        data.update(header)
        chosen = table["rows"][table["chosen"]]
        data["rows"][str(table["seed"])] = {
            "iod": chosen["iod"], "ood": chosen["ood"], "w_ug08": chosen["w_ug08"],
            "spurious": chosen["spurious"], "coefficients": chosen["coefficients"],
            "chosen": table["chosen"], "seconds": None, "hybrid_parameters": None}
    save(path, data)
    print(format_summary(load(path)))
    return 0


def format_row(row: dict) -> str:
    def fmt(value):
        return "—" if value is None else f"{value:.3f}"

    verdict = meets(row)
    text = (f"{fmt(row.get('iod'))} / {fmt(row.get('ood'))} %, {row['coefficients']} coefficients, "
            f"W {fmt(row.get('w_ug08'))}, spurious {row.get('spurious') or 'none'}")
    if "op_dq" in row:
        text += ", ΔQ op. " + ("no equilibrium" if row["op_dq"] is None else f"{row['op_dq']:.3g}")
    if row.get("seconds") is not None:
        text += f", {row['seconds']:.0f} s"
        if row.get("cpu_seconds") is not None:
            text += f" (CPU {row['cpu_seconds']:.0f} s)"
    if verdict["accuracy"] and verdict["no_spurious"]:
        text += " [accuracy]"
    if verdict["compression"]:
        text += " [compression]"
    if verdict["operating_point"] is False:
        text += " [operating point wrong]"
    if verdict["microgrid"] is not None:
        from microgrid_bench import WEAK_X

        text += f", microgrid {row['mg_max_real'] if row['mg_max_real'] is None else round(row['mg_max_real'], 3)}"
        weak = [x for x, w in zip(WEAK_X, row.get("weak_max_real") or []) if wrong_verdict(w)]
        text += f", weak grid unstable at x {weak}" if weak else ""
        text += " [microgrid wrong]" if verdict["microgrid"] is False else ""
        text += " [flagged by its alternatives]" if verdict["microgrid_wrong_flagged"] else ""
        text += " [false alarm of its alternatives]" if verdict["microgrid_false_alarm"] else ""
    return text


def format_summary(data: dict) -> str:
    s = summary(list(data["rows"].values()))
    text = (f"{data.get('name')}: {s['recordings']} recordings; IOD/OOD within the targets with no spurious mode "
            f"{s['accuracy_and_no_spurious']}, spurious {s['spurious']}, compression {s['compression']}, "
            f"every target {s['all_targets']}")
    if s["recordings"]:
        text += (f"; IOD median {s['iod_median']:.3f} worst {s['iod_worst']:.3f} %, OOD median "
                 f"{s['ood_median']:.3f} worst {s['ood_worst']:.3f} %, coefficients median {s['coefficients_median']:.0f}")
    if s["operating_point_measured"]:
        text += (f"; operating point wrong (ΔQ above {OPERATING_POINT_DQ_LIMIT} p.u. or no equilibrium) "
                 f"{s['operating_point_wrong']} of {s['operating_point_measured']} measured")
    if s["microgrid_measured"]:
        text += (f"; microgrid or weak-grid verdict wrong {s['microgrid_wrong']} of "
                 f"{s['microgrid_measured']} measured, {s['microgrid_wrong_flagged']} of those flagged by the "
                 f"model's alternatives, {s['microgrid_false_alarms']} false alarms; of the "
                 f"{s['microgrid_points']} verdicts, {s['microgrid_points_wrong']} wrong, "
                 f"{s['microgrid_points_wrong_flagged']} of those and {s['microgrid_points_right_flagged']} right "
                 f"ones flagged open")
    if "seconds_median" in s:
        text += f", time median {s['seconds_median']:.1f} worst {s['seconds_worst']:.1f} s"
    if "cpu_seconds_median" in s:
        text += f" (CPU median {s['cpu_seconds_median']:.1f} s)"
    return text


def compare(args) -> int:
    tables = [load(Path(p)) for p in args.files]
    common = sorted(set.intersection(*(set(t["rows"]) for t in tables)), key=int)
    if not common:
        raise SystemExit("setting_sweep: the files share no recording")
    for seed in common:
        print(f"seed {seed:>2}")
        for t in tables:
            print(f"   {str(t.get('name'))[:24]:24s} {format_row(t['rows'][seed])}")
    print(f"over the {len(common)} recordings in every file:")
    for t in tables:
        print("  ", format_summary({**t, "rows": {k: t["rows"][k] for k in common}}))
    return 0


def main(argv=None) -> int:
    from bench import add_settings_option

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_run = sub.add_parser("run", help="fit PISML with a setting on each recording and score the chosen model")
    p_run.add_argument("--name", required=True, help="the sweep's name (bench/sweeps/NAME.json)")
    add_settings_option(p_run)
    p_run.add_argument("--seeds", default="0-15", help="recordings, e.g. 0-15 or 0,2,5 (default 0-15)")
    p_run.add_argument("--scenario", default="protocol", help="a scenario of bench/scenarios_bench.py")
    p_run.add_argument("--noise", default="40", help="'clean' or an SNR in dB (default 40)")
    p_run.add_argument("--out", help="the sweep file (default bench/sweeps/NAME.json)")
    p_run.add_argument("--models", help="a folder to keep each chosen model in (NAME_SEED.json)")
    p_run.set_defaults(func=run)
    p_cmp = sub.add_parser("compare", help="the recordings' rows of sweep files side by side, and their counts")
    p_cmp.add_argument("files", nargs="+")
    p_cmp.set_defaults(func=compare)
    p_imp = sub.add_parser("import", help="a sweep file from bench/candidates.py --out files")
    p_imp.add_argument("--name", required=True)
    p_imp.add_argument("--out")
    p_imp.add_argument("files", nargs="+")
    p_imp.set_defaults(func=import_tables)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
