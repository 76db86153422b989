"""Replay a choice between two settings' models from their sweep rows, without fitting again.

Stop 59's question: ``filter_terms`` "physics" compresses (≤ 84 coefficients on 21 of the 24
protocol recordings) where the default "any" does not, and each meets both 40 dB accuracy targets
on 14 of 24 with no spurious mode, on different recordings. Could a fit run the second setting's
refinement only where the first one's choice scores high, and keep the family whose best model
scores better? The rows of ``bench/setting_sweep.py run`` keep every candidate's training error
(``selection``), so that rule can be replayed: for each ratio τ, where the first setting's chosen
model scores above τ × its noise floor, the recording takes the second setting's row if that
family's best eligible score (as engine step 6 counts eligibility: below the hold, fewest
inconsistent rest points) is lower, else the first's. The times are the rows' own: a fit that ran
both refinements would take about their sum.

    .venv/bin/python bench/family_choice.py bench/sweeps/filter-physics-stop59.json \\
        bench/sweeps/default-stop59-selection.json [--ratios 0,1.5,2.5]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parents[1])]

from setting_sweep import format_summary, load  # noqa: E402


def best_eligible(row: dict) -> tuple:
    """(fewest inconsistent rest points among the eligible candidates, their best score) of one row's
    selection record, by the engine's own rule (:func:`pisml_ros.ident.selection.eligible_candidates`),
    and the chosen model's score over the noise floor."""
    from pisml_ros.ident.selection import eligible_candidates

    selection = row.get("selection")
    if not selection:
        raise SystemExit("family_choice: a row without 'selection' (swept before stop 59): run the sweep again")
    scores = {name: np.inf if value is None else value for name, value in selection["training_error_pct"].items()}
    recorded = selection["inconsistent_rest_points"]
    _, misfits, eligible = eligible_candidates(
        scores, selection["hold_error_pct"], lambda name: np.inf if recorded.get(name) is None else recorded[name])
    best = min(eligible, key=lambda name: scores[name])
    floor = selection.get("noise_floor_pct") or np.nan
    return (misfits[best], scores[best]), scores[row["chosen"]] / floor


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", help="sweep file of the setting that runs first")
    parser.add_argument("second", help="sweep file of the setting run where the first's choice scores high")
    parser.add_argument("--ratios", default="0,1.3,1.5,1.7,2,2.5", help="τ values, comma-separated")
    args = parser.parse_args(argv)
    first, second = load(Path(args.first))["rows"], load(Path(args.second))["rows"]
    seeds = sorted(set(first) & set(second), key=int)
    print(f"{len(seeds)} recordings in both files")
    for path, rows in ((args.first, first), (args.second, second)):
        print(format_summary({"name": Path(path).stem, "rows": {k: rows[k] for k in seeds}}))
    for tau in (float(v) for v in args.ratios.split(",")):
        rows, runs = {}, 0
        for k in seeds:
            mine, ratio = best_eligible(first[k])
            if ratio > tau:
                runs += 1
                theirs, _ = best_eligible(second[k])
                rows[k] = second[k] if theirs < mine else first[k]
            else:
                rows[k] = first[k]
        print(format_summary({"name": f"τ {tau:g} (the second setting run on {runs})", "rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
