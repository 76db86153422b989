"""Replay the engine's selection on saved candidate tables, under other selection settings.

``bench/candidates.py --out FILE`` keeps every candidate of one fit as an explicit model, its test
errors (IOD / OOD, spurious modes) and the fit's selection record (hold error, noise floor). This
script runs the engine's own selection (:func:`pisml_ros.ident.selection._configured_selection`)
again on those candidates with the settings given by ``--set`` and prints, per table, the model
the fit chose, the one the replay chooses and their test errors, then how many replayed choices
are within both 40 dB targets (IOD ≤ 0.5 %, OOD ≤ 1.0 %, no spurious mode), and in how many fits
any candidate is (the ceiling of every selection rule: stop 79, 38 of 48 on recordings 24–71
against the engine's 28).

A replay sees only the final candidates: where a setting would have changed what the fit ran
(a rescue, a second start), only a fit measures it. Stop 75 (``selection_decay_margin``)::

    for s in $(seq 0 23); do .venv/bin/python bench/candidates.py --seed $s --noise 40 --out c-$s.json; done
    .venv/bin/python bench/selection_replay.py c-*.json --set selection_decay_margin=0
    .venv/bin/python bench/selection_replay.py c-*.json

One fit on low-SNR records (``IdentConfig.low_snr_below_db``; 40 dB ones with ``--set low_snr_below_db=inf``)
gives the choices with the second refinement pass and the short-window check and without them (stop 96,
35 dB): ``--first-pass-only --no-window-check`` replays a fit on records that do not count as low-SNR
(the first pass's candidates do not depend on that setting)::

    .venv/bin/python bench/selection_replay.py c35-*.json --first-pass-only --no-window-check
    .venv/bin/python bench/selection_replay.py c35-*.json   # as fitted: both passes and the short windows
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent
sys.path[:0] = [str(BENCH), str(BENCH.parent)]


def replayed_choice(table: dict, config, first_pass_only: bool = False, window_check: bool = True) -> str:
    """The candidate the selection configured by ``config`` (IdentConfig) takes among ``table``'s
    (a ``bench/candidates.py --out`` file's contents). ``first_pass_only`` leaves out the low-SNR
    pass's candidates (names with ``estimators.LOW_SNR_SUFFIX``) and ``window_check=False`` the short
    windows' costs the fit judged: with both, a table fitted on low-SNR records
    replays the choice of a fit where the records do not count as low-SNR (the first pass's candidates
    do not depend on that setting)."""
    from pisml_ros.ident.estimators import LOW_SNR_SUFFIX
    from pisml_ros.ident.selection import _configured_selection
    from pisml_ros.model import ExplicitModel

    models = {name: ExplicitModel.from_dict(model, source=name) for name, model in table["models"].items()
              if not (first_pass_only and name.endswith(LOW_SNR_SUFFIX))}
    recorded = table["selection"]
    scores = {name: np.inf if recorded["training_error_pct"].get(name) is None
              else recorded["training_error_pct"][name] for name in models}
    first = next(iter(models.values()))
    # candidates.py gave every candidate the fit's rest points; the roles come from the config
    template = ExplicitModel(first.state_names, first.input_names, first.terms, first.coefficients,
                             {"reference_points": first.metadata.get("reference_points") or [],
                              "config": config.to_dict()})
    floor = recorded.get("noise_floor_pct")
    noisy = recorded.get("tolerance_floor_pct") is not None
    # the short windows' costs where the fit judged them (low-SNR records: IdentConfig.selection_window_excess)
    selection = _configured_selection(template, models, scores, config, {}, recorded["hold_error_pct"],
                                      noise_floor=floor, tolerance_floor=floor if noisy else None,
                                      window_costs=recorded.get("window_costs") if window_check else None)
    return selection.metadata["selection"]["chosen"]


def percent(value) -> str:
    """An error (%) as the tables print it; a run that could not be scored (None) as a dash."""
    return "—" if value is None else f"{value:.3f}"


def within(row: dict) -> bool:
    """Both 40 dB accuracy targets met and no spurious unstable mode (as ``bench/setting_sweep.py`` judges)."""
    from setting_sweep import meets

    met = meets(row)
    return met["accuracy"] and met["no_spurious"]


def main(argv=None) -> int:
    from bench import add_settings_option, settings_or_exit
    from setting_sweep import meets

    from pisml_ros.ident import IdentConfig

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tables", nargs="+", help="bench/candidates.py --out files")
    parser.add_argument("--first-pass-only", action="store_true",
                        help="leave out the candidates of the low-SNR refinement pass (IdentConfig."
                             "refine_growing_windows_low_snr)")
    parser.add_argument("--no-window-check", action="store_true",
                        help="ignore the short windows' costs the fit judged (IdentConfig.selection_window_excess)")
    add_settings_option(parser)
    args = parser.parse_args(argv)
    config = IdentConfig.load(None, settings_or_exit(args.set, parser))
    rows, reachable = [], 0
    limited: dict = {"selection": [], "fit": []}  # the seeds outside, by what could mend them
    for path in args.tables:
        try:
            table = json.loads(Path(path).read_text())
            fitted = table["chosen"]
            chosen = replayed_choice(table, config, args.first_pass_only, not args.no_window_check)
        except (OSError, ValueError, KeyError) as err:
            parser.error(f"{path}: not a bench/candidates.py --out table ({type(err).__name__}: {err})")
        row = table["rows"][chosen]
        rows.append(row)
        # the selection's ceiling: some candidate of the fit is within, whichever rule finds it
        inside = sum(within(r) for r in table["rows"].values())
        reachable += inside > 0
        before = table["rows"][fitted]
        mark = "same" if chosen == fitted else f"was {fitted!r} ({percent(before['iod'])} / {percent(before['ood'])} %)"
        met = within(row)
        if not met:
            # another choice among this fit's candidates could mend it, or only a better fit
            kind = "selection" if inside else "fit"
            limited[kind].append(str(table["seed"]))
            mark += f"; {kind}-limited ({inside} candidate{'s' if inside != 1 else ''} within)"
        print(f"{table['scenario']} {table['plant']} seed {table['seed']} {table['noise']}: {chosen!r} "
              f"{percent(row['iod'])} / {percent(row['ood'])} %, {row['coefficients']} coefficients, "
              f"{'within' if met else 'OUTSIDE'}; {mark}")
    median = {key: statistics.median(np.inf if r[key] is None else r[key] for r in rows) for key in ("iod", "ood")}
    print(f"{sum(map(within, rows))} of {len(rows)} within both 40 dB targets with no spurious mode; "
          f"median IOD {median['iod']:.3f} %, OOD {median['ood']:.3f} %; at most 84 coefficients: "
          f"{sum(meets(r)['compression'] for r in rows)}")
    print(f"a candidate within both targets with no spurious mode exists in {reachable} of {len(rows)} fits "
          "(what a selection could reach; the others only a better fit can mend)")
    if any(limited.values()):
        print(f"outside: selection-limited seeds {', '.join(limited['selection']) or 'none'}; "
              f"fit-limited seeds {', '.join(limited['fit']) or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
