"""bench/selection_replay.py: the engine's selection replayed on a saved candidate table (no fit runs here)."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import selection_replay  # noqa: E402

from pisml_ros.model import ExplicitModel  # noqa: E402


def _table(tmp_path):
    """A bench/candidates.py --out table of two candidates of a noisy fit: x' = rate (ug - x), the
    better-scoring one's mode at -0.03 1/s at the small-signal rest point, the other's at -0.5."""
    points = [{"inputs": [0.8], "state": [0.8], "smallsignal": True}, {"inputs": [1.0], "state": [1.0]}]

    def model(rate):
        return ExplicitModel(("x",), ("ug",), ["ug", "x"], np.array([[rate], [-rate]]),
                             {"reference_points": points}).to_dict()

    def row(iod, ood):
        return {"iod": iod, "ood": ood, "spurious": [], "coefficients": 2}

    table = {"scenario": "protocol", "plant": "standard", "seed": 1, "noise": 40.0, "chosen": "pruned +0.1 % x3",
             "models": {"pruned +0.1 % x3": model(0.03), "pruned +0.1 % x3 at long windows": model(0.5)},
             "rows": {"pruned +0.1 % x3": row(0.278, 1.224), "pruned +0.1 % x3 at long windows": row(0.269, 0.546)},
             "selection": {"training_error_pct": {"pruned +0.1 % x3": 2.8, "pruned +0.1 % x3 at long windows": 3.3},
                           "hold_error_pct": 40.0, "noise_floor_pct": 1.8, "tolerance_floor_pct": 1.8}}
    path = tmp_path / "c-1.json"
    path.write_text(json.dumps(table))
    return path


def test_the_replay_takes_the_settings_given_and_reports_the_targets(tmp_path, capsys):
    path = _table(tmp_path)
    assert selection_replay.main([str(path), "--set", "selection_decay_margin=0"]) == 0
    off = capsys.readouterr().out
    assert "'pruned +0.1 % x3' 0.278 / 1.224 %" in off and "OUTSIDE; same" in off
    assert "0 of 1 within both 40 dB targets" in off
    assert "a candidate within both targets with no spurious mode exists in 1 of 1 fits" in off
    # the miss is the selection's: another candidate of the same fit is within
    assert "OUTSIDE; same; selection-limited (1 candidate within)" in off
    assert "outside: selection-limited seeds 1; fit-limited seeds none" in off
    assert selection_replay.main([str(path)]) == 0  # the default margin, 0.1 1/s
    on = capsys.readouterr().out
    assert "'pruned +0.1 % x3 at long windows' 0.269 / 0.546 %" in on and "was 'pruned +0.1 % x3'" in on
    assert "1 of 1 within both 40 dB targets" in on and "outside:" not in on


def test_the_replay_names_a_file_that_is_no_candidate_table(tmp_path, capsys):
    bad = tmp_path / "results.json"
    bad.write_text(json.dumps({"runs": []}))
    with pytest.raises(SystemExit):
        selection_replay.main([str(bad)])
    assert f"{bad}: not a bench/candidates.py --out table (KeyError" in capsys.readouterr().err


def test_the_replay_judges_the_short_window_costs_a_low_snr_fit_recorded(tmp_path, capsys):
    """A fit on low-SNR records keeps its candidates' short-window costs in the selection record: the
    replay applies ``selection_window_excess`` to them as the fit did, and not where it is switched off."""
    path = _table(tmp_path)
    table = json.loads(path.read_text())
    # the margin off, the better score wins unless the short windows reject it (22 x 50 = 1100 > 300)
    table["selection"]["window_costs"] = {"pruned +0.1 % x3": 2900.0, "pruned +0.1 % x3 at long windows": 2850.0}
    path.write_text(json.dumps(table))
    assert selection_replay.main([str(path), "--set", "selection_decay_margin=0"]) == 0
    judged = capsys.readouterr().out
    assert "'pruned +0.1 % x3 at long windows' 0.269 / 0.546 %" in judged
    assert selection_replay.main([str(path), "--set", "selection_decay_margin=0",
                                  "--set", "selection_window_excess=0"]) == 0
    assert "'pruned +0.1 % x3' 0.278 / 1.224 %" in capsys.readouterr().out


def test_the_replay_can_leave_out_the_low_snr_pass_and_the_short_window_costs(tmp_path, capsys):
    """A table fitted on low-SNR records (``low_snr_below_db``) replays the choice of a fit on records that
    do not count as low-SNR: ``--first-pass-only`` drops the candidates named with LOW_SNR_SUFFIX and
    ``--no-window-check`` the short windows' costs the fit recorded."""
    from pisml_ros.ident.estimators import LOW_SNR_SUFFIX

    path = _table(tmp_path)
    table = json.loads(path.read_text())
    second = "pruned +0.1 % x3" + LOW_SNR_SUFFIX
    table["models"][second] = table["models"]["pruned +0.1 % x3 at long windows"]
    table["rows"][second] = {"iod": 0.211, "ood": 0.432, "spurious": [], "coefficients": 2}
    table["selection"]["training_error_pct"][second] = 2.5  # the best score
    table["selection"]["window_costs"] = {"pruned +0.1 % x3": 2900.0, "pruned +0.1 % x3 at long windows": 2850.0,
                                          second: 2851.0}
    path.write_text(json.dumps(table))
    settings = ["--set", "selection_decay_margin=0"]
    assert selection_replay.main([str(path), *settings]) == 0
    assert f"'{second}' 0.211 / 0.432 %" in capsys.readouterr().out
    # without the second pass the short windows reject the better-scoring first-pass candidate
    assert selection_replay.main([str(path), *settings, "--first-pass-only"]) == 0
    assert "'pruned +0.1 % x3 at long windows' 0.269 / 0.546 %" in capsys.readouterr().out
    # and without their costs too, the better score wins, as in a fit on records that are not low-SNR
    assert selection_replay.main([str(path), *settings, "--first-pass-only", "--no-window-check"]) == 0
    assert "'pruned +0.1 % x3' 0.278 / 1.224 %" in capsys.readouterr().out
