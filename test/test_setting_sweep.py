"""bench/setting_sweep.py: the per-recording target counts and the sweep files (no fitting here)."""
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import setting_sweep  # noqa: E402


def _row(iod, ood, coefficients, spurious=(), hybrid=None):
    return {"iod": iod, "ood": ood, "coefficients": coefficients, "spurious": list(spurious),
            "w_ug08": 3.0, "hybrid_parameters": hybrid, "seconds": None, "chosen": "pruned +0.1 % x3"}


def test_seeds_parse_ranges_and_reject_words():
    assert setting_sweep.parse_seeds("0-3,7,2") == [0, 1, 2, 3, 7]
    with pytest.raises(ValueError, match="--seeds 'a-b'"):
        setting_sweep.parse_seeds("a-b")


def test_a_recording_meets_each_target_on_its_own_figures():
    good = setting_sweep.meets(_row(0.3, 0.6, 80))
    assert good == {"accuracy": True, "no_spurious": True, "compression": True, "all": True, "operating_point": None,
                    "microgrid": None, "microgrid_wrong_flagged": False, "microgrid_false_alarm": False}
    # compression from the hybrid's own count where the row has it, else the default hybrid's 84
    assert setting_sweep.meets(_row(0.3, 0.6, 90, hybrid=21000))["compression"] is False
    assert setting_sweep.meets(_row(0.3, 0.6, 90, hybrid=30000))["compression"] is True
    spurious = setting_sweep.meets(_row(0.3, 0.6, 80, spurious=[0.2]))
    assert spurious["accuracy"] and not spurious["no_spurious"] and not spurious["all"]
    assert not setting_sweep.meets(_row(None, None, 80))["accuracy"]  # a failed simulation
    counts = setting_sweep.summary([_row(0.3, 0.6, 80), _row(0.6, 0.6, 120), _row(0.3, 0.6, 90, spurious=[0.4])])
    assert (counts["accuracy_and_no_spurious"], counts["spurious"], counts["compression"], counts["all_targets"]) \
        == (1, 1, 1, 1)
    assert counts["iod_worst"] == 0.6 and counts["coefficients_median"] == 90
    # wall and CPU times where the rows have them (CPU since stop 67: the machine's speed drifts)
    timed = [dict(_row(0.3, 0.6, 80), seconds=50.0, cpu_seconds=90.0), dict(_row(0.3, 0.6, 80), seconds=70.0)]
    counts = setting_sweep.summary(timed)
    assert counts["seconds_median"] == 60.0 and counts["cpu_seconds_median"] == 90.0
    assert "50 s (CPU 90 s)" in setting_sweep.format_row(timed[0]) and "CPU" not in setting_sweep.format_row(timed[1])
    assert "time median 60.0 worst 70.0 s (CPU median 90.0 s)" in setting_sweep.format_summary(
        {"name": "x", "rows": dict(enumerate(timed))})


def test_microgrid_verdicts_count_against_the_plants():
    stable = dict(_row(0.3, 0.6, 80), mg_max_real=-0.5, weak_max_real=[-0.4, -0.3])
    assert setting_sweep.meets(stable)["microgrid"] is True
    # unstable in the microgrid, behind one weak line, or without an operating point there: wrong
    assert setting_sweep.meets(dict(stable, mg_max_real=0.1))["microgrid"] is False
    assert setting_sweep.meets(dict(stable, mg_max_real=None))["microgrid"] is False
    assert setting_sweep.meets(dict(stable, weak_max_real=[-0.4, 0.02]))["microgrid"] is False
    assert setting_sweep.meets(dict(stable, weak_max_real=[-0.4, None]))["microgrid"] is False
    counts = setting_sweep.summary([stable, dict(stable, mg_max_real=0.1), _row(0.3, 0.6, 80)])
    assert (counts["microgrid_wrong"], counts["microgrid_measured"]) == (1, 2)
    text = setting_sweep.format_row(dict(stable, weak_max_real=[-0.4] * 8 + [0.2]))
    assert "weak grid unstable at x [1.5]" in text and "[microgrid wrong]" in text
    # the alternatives: a wrong verdict they contradict is flagged, a right one they contradict is a false alarm
    wrong = dict(stable, mg_max_real=0.1, mg_alternatives=[-0.3], weak_alternatives=[[-0.4], [-0.3]])
    assert setting_sweep.meets(wrong)["microgrid_wrong_flagged"] and not setting_sweep.meets(wrong)["microgrid_false_alarm"]
    unflagged = dict(wrong, mg_alternatives=[0.2])
    assert not setting_sweep.meets(unflagged)["microgrid_wrong_flagged"]
    alarm = dict(stable, mg_alternatives=[], weak_alternatives=[[0.1], [None]])
    assert setting_sweep.meets(alarm)["microgrid_false_alarm"] and setting_sweep.meets(alarm)["microgrid"]
    counts = setting_sweep.summary([wrong, unflagged, alarm])
    assert (counts["microgrid_wrong"], counts["microgrid_wrong_flagged"], counts["microgrid_false_alarms"]) == (2, 1, 1)
    # per verdict: wrong's grid-tied point (wrong, flagged), unflagged's (wrong, not), alarm's two weak lines (flagged)
    assert (counts["microgrid_points"], counts["microgrid_points_wrong"], counts["microgrid_points_wrong_flagged"],
            counts["microgrid_points_right_flagged"]) == (9, 2, 1, 2)


def test_quick_verdicts_of_the_plant_are_stable():
    import microgrid_bench

    verdicts = microgrid_bench.quick_verdicts(None)
    assert verdicts["grid_tied_max_real"] == pytest.approx(-1.532, abs=0.01)
    assert len(verdicts["weak_max_real"]) == len(microgrid_bench.WEAK_X)
    assert max(verdicts["weak_max_real"]) < -1.0
    assert verdicts["grid_tied_alternatives"] == [] and verdicts["weak_alternatives"] == [[]] * len(microgrid_bench.WEAK_X)


def test_candidate_tables_import_into_a_sweep_that_compare_reads(tmp_path, capsys):
    tables = []
    for seed, (iod, n) in enumerate([(0.2, 78), (0.7, 95)]):
        path = tmp_path / f"cp{seed}.json"
        path.write_text(json.dumps({"scenario": "protocol", "seed": seed, "noise": "40", "settings": {},
                                    "chosen": "pruned +0.1 % x3",
                                    "rows": {"pruned +0.1 % x3": {"iod": iod, "ood": 0.5, "w_ug08": 4.0,
                                                                  "spurious": [], "coefficients": n}}}))
        tables.append(str(path))
    out = tmp_path / "sweeps" / "default.json"
    assert setting_sweep.main(["import", "--name", "default", "--out", str(out), *tables]) == 0
    saved = json.loads(out.read_text())
    assert set(saved["rows"]) == {"0", "1"} and saved["summary"]["all_targets"] == 1
    assert setting_sweep.main(["compare", str(out), str(out)]) == 0
    assert "every target 1" in capsys.readouterr().out
    # another noise level's table does not go into the same sweep
    other = json.loads(Path(tables[0]).read_text()) | {"noise": "clean", "seed": 5}
    Path(tables[0]).write_text(json.dumps(other))
    with pytest.raises(SystemExit, match="another scenario, noise or setting"):
        setting_sweep.main(["import", "--name", "x", "--out", str(tmp_path / "x.json"), tables[1], tables[0]])


def test_benchmark_scripts_take_settings_and_stop_on_a_bad_one_before_any_fit(capsys):
    import bench
    import candidates
    import microgrid_bench
    import plants_bench
    import scenarios_bench

    assert bench.settings_or_exit([" filter_terms = physics", "", "epochs=3"]) == {"filter_terms": "physics",
                                                                                    "epochs": "3"}
    # a malformed item, an unknown key, a bad value: each named, and no fit started (these would take minutes)
    for main, argv, named in [(scenarios_bench.main, ["--set", "epochs"], "'epochs' is not KEY=VALUE"),
                              (plants_bench.main, ["--set", "bogus=1"], "unknown key(s) ['bogus']"),
                              (bench.main, ["--quick", "--set", "filter_terms=linear"],
                               "filter_terms must be physics or any, got 'linear'"),
                              (candidates.main, ["--set", "epochs=0"], "epochs must be > 0"),
                              (microgrid_bench.main, ["--set", "filter_terms=linear"],
                               "filter_terms must be physics or any, got 'linear'"),
                              (setting_sweep.main, ["run", "--name", "x", "--set", "selection_tolerance=-1"],
                               "selection_tolerance")]:
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert named in str(stop.value) + capsys.readouterr().err


def test_the_input_noise_scenarios_put_noise_on_the_inputs_at_their_level():
    import scenarios_bench

    _, protocol, _, _ = scenarios_bench.scenario_datasets(scenarios_bench.SCENARIOS["protocol"], 40.0, 0)
    _, noisy, noisy_small, _ = scenarios_bench.scenario_datasets(scenarios_bench.SCENARIOS["noisy inputs"], 40.0, 0)
    _, quieter, _, _ = scenarios_bench.scenario_datasets(scenarios_bench.SCENARIOS["inputs 20 dB quieter"], 40.0, 0)
    assert protocol.metadata["noise_std"]["ug"] == 0.0 and noisy_small.metadata["noise_std"]["ug"] > 0
    assert quieter.metadata["noise_std"]["ug"] == pytest.approx(0.1 * noisy.metadata["noise_std"]["ug"])
    # the states' noise is the protocol's draw in all three
    for other in (noisy, quieter):
        assert all((a.x == b.x).all() for a, b in zip(protocol, other))


def test_a_family_choice_replay_takes_the_second_setting_only_above_the_ratio_and_where_it_scores_better(
        tmp_path, capsys):
    import family_choice

    def sweep(name, rows):
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps({"name": name, "rows": rows}))
        return str(path)

    def row(iod, coefficients, scores, inconsistent, chosen):
        return _row(iod, 0.5, coefficients) | {"chosen": chosen, "selection": {
            "training_error_pct": scores, "inconsistent_rest_points": inconsistent,
            "hold_error_pct": 40.0, "noise_floor_pct": 1.0}}

    # recording 0: the first setting's choice at 3x its floor, the second family's best eligible
    # model better (its lower score belongs to a model inconsistent with a rest point, which does
    # not count); recording 1: at 1.5x, the second family's best worse
    first = sweep("first", {"0": row(0.9, 60, {"a": 3.0}, {"a": 0}, "a"),
                            "1": row(0.2, 70, {"a": 1.5}, {"a": 0}, "a")})
    second = sweep("second", {"0": row(0.3, 90, {"b": 2.0, "c": 1.0}, {"b": 0, "c": 1}, "b"),
                              "1": row(0.4, 95, {"b": 1.6}, {"b": 0}, "b")})
    assert family_choice.main([first, second, "--ratios", "0,2,5"]) == 0
    lines = capsys.readouterr().out.splitlines()
    # τ 0: recording 0 takes the second's row (0.3 %), recording 1 keeps the first's: both within
    assert lines[3].startswith("τ 0 (the second setting run on 2)") and "no spurious mode 2" in lines[3]
    assert lines[4].startswith("τ 2 (the second setting run on 1)") and "no spurious mode 2" in lines[4]
    assert lines[5].startswith("τ 5 (the second setting run on 0)") and "no spurious mode 1" in lines[5]
    with pytest.raises(SystemExit, match="without 'selection'"):
        family_choice.main([sweep("old", {"0": _row(0.2, 0.5, 70)}), second])


def test_a_row_says_where_the_operating_point_went_wrong(capsys):
    off = _row(0.3, 0.6, 80) | {"op_dp": 0.001, "op_dq": 1.5}
    none = _row(0.3, 0.6, 80) | {"op_dp": None, "op_dq": None}  # no equilibrium at a grid point
    right = _row(0.3, 0.6, 80) | {"op_dp": 0.001, "op_dq": 0.05}
    assert [setting_sweep.meets(r)["operating_point"] for r in (off, none, right, _row(0.3, 0.6, 80))] \
        == [False, False, True, None]  # the last: a row from before stop 60, not measured
    # the targets stay what they were; the operating point is counted beside them
    assert setting_sweep.meets(off)["all"]
    counts = setting_sweep.summary([off, none, right, _row(0.3, 0.6, 80)])
    assert (counts["operating_point_wrong"], counts["operating_point_measured"]) == (2, 3)
    assert "[operating point wrong]" in setting_sweep.format_row(off) and "ΔQ op. 1.5" in setting_sweep.format_row(off)
    assert "ΔQ op. no equilibrium" in setting_sweep.format_row(none)
    assert "operating point wrong (ΔQ above 0.3 p.u. or no equilibrium) 2 of 3 measured" in \
        setting_sweep.format_summary({"name": "x", "rows": {"0": off, "1": none, "2": right, "3": _row(0.3, 0.6, 80)}})


def test_a_scored_row_measures_the_models_operating_point_against_the_plant():
    import bench

    from pisml_ros.model.explicit import ExplicitModel

    plant, _, _, test = bench.datasets({}, 40.0, seed=0)
    grid = bench.plant_grid(plant)
    truth = {g: plant.eigenvalues(g, 0.0) for g in grid}
    root = Path(__file__).resolve().parents[1] / "bench"
    model = ExplicitModel.load(root / "models" / "standard_40dB_pisml.json")
    row = setting_sweep.scored_row(model, plant, test, grid, truth)
    # the figures make bench wrote for the same model (bench/results.json, recording 0)
    benchmark = next(run for run in json.loads((root / "results.json").read_text())["runs"]
                     if run["case"] == "standard/40 dB" and run["method"] == "pisml" and run.get("sweep") == "main")
    for key in ("iod", "ood", "op_dq", "op_dp"):
        assert row[key] == pytest.approx(benchmark[key], rel=1e-6), key
    assert row["coefficients"] == benchmark["n_parameters"]
    assert setting_sweep.meets(row)["operating_point"] is (benchmark["op_dq"] <= setting_sweep.OPERATING_POINT_DQ_LIMIT)


def test_the_rest_hold_is_the_models_drift_from_the_plants_rest_when_the_input_first_changes():
    import candidates
    from pisml_ros.data.dataset import Trajectory

    t = np.arange(6) * 1e-3
    u = np.array([[1.0, 0.0]] * 3 + [[1.0, 0.5]] * 3)  # the angle jumps after the third sample
    truth = Trajectory(0, t, np.ones((6, 4)), u)
    drifting = Trajectory(0, t, np.ones((6, 4)) + np.outer(t, [1.0, -2.0, 0.0, 0.5]), u)
    hold = candidates.rest_hold(drifting, truth, [0, 1, 2, 3])
    assert hold["seconds"] == pytest.approx(2e-3)
    assert hold["drift"] == pytest.approx({"ig_d": 2e-3, "ig_q": -4e-3, "vc_d": 0.0, "vc_q": 1e-3})
    assert candidates._drift_text(hold) == "ig_d +0.0020 in 2 ms"
    # inputs that change at once leave no rest to hold
    ramp = Trajectory(0, t, np.ones((6, 4)), np.outer(t, [1.0, 1.0]))
    assert candidates.rest_hold(drifting, ramp, [0, 1, 2, 3]) is None
