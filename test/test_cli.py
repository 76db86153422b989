"""The `pisml` command as a user runs it: outputs, exit statuses, one-line errors."""
import csv
import json

import numpy as np
import pytest

from pisml_ros.signals import INPUT_NAMES, STATE_NAMES

from cli_helpers import pisml


def test_simulate_csv_opens_in_a_plain_csv_reader(tmp_path):
    out = tmp_path / "train.csv"
    pisml("simulate", "--scenario", "train", "--snr-db", "40", "--seed", "3", "--n-traj", "2", "--out", out)
    with open(out, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["traj", "t", *STATE_NAMES, *INPUT_NAMES]
    assert len(rows) == 1 + 2 * 401
    side = json.loads(out.with_suffix(".json").read_text())
    assert side["snr_db"] == 40 and side["seed"] == 3 and side["dt"] == 1e-4
    assert side["noise_std"]["ug"] == 0.0  # the protocol's: exact inputs
    noisy = tmp_path / "noisy.csv"
    assert "40 dB SNR on inputs too" in pisml("simulate", "--scenario", "train", "--snr-db", "40", "--noisy-inputs",
                                              "--n-traj", "2", "--out", noisy).stdout
    assert json.loads(noisy.with_suffix(".json").read_text())["noise_std"]["ug"] > 0.005
    refused = pisml("simulate", "--scenario", "train", "--noisy-inputs", "--out", tmp_path / "x.csv", check=False)
    assert refused.returncode != 0 and "--noisy-inputs needs --snr-db" in refused.stderr


def test_simulate_bag_with_effect_and_info(tmp_path):
    bag = tmp_path / "sag_bag"
    pisml("simulate", "--scenario", "test", "--effect", "current_limit", "--effect-param", "current_limit.imax=1.3",
          "--out", bag)
    assert (bag / "metadata.yaml").is_file()
    info = json.loads(pisml("data", "info", bag, "--json").stdout)
    assert info["trajectories"] == 2 and info["metadata"]["effects"]["current_limit"]["imax"] == 1.3
    text = pisml("data", "info", bag).stdout
    assert "2 trajectories" in text and "ig_q" in text


def test_simulate_says_which_record_cannot_start_at_rest_under_a_tight_limit(tmp_path):
    # the training scenario's 5th record starts at ug 1.2, where a 1.5 p.u. current limit leaves no equilibrium
    refused = pisml("simulate", "--scenario", "train", "--n-traj", "5", "--effect-param", "current_limit.imax=1.5",
                    "--out", tmp_path / "never", check=False)
    assert refused.returncode == 2 and "Traceback" not in refused.stderr, refused.stderr
    assert "trajectory 4 starts at rest at ug0 = 1.199" in refused.stderr and "current_limit" in refused.stderr
    assert not (tmp_path / "never").exists()


def test_analyse_plant_json():
    report = json.loads(pisml("analyse", "--model", "plant", "--ug", "0.8", "--theta-g", "0", "--json").stdout)
    assert set(report) >= {"operating_point", "eigenvalues", "damping", "max_real", "stable"}
    eig = np.array([complex(re, im) for re, im in report["eigenvalues"]])
    assert len(eig) == 13 and report["stable"] is True
    assert np.min(np.abs(eig - complex(-653.40, 9760.44))) < 0.5
    unstable = json.loads(pisml("analyse", "--ug", "1.2", "--json").stdout)
    assert unstable["stable"] is False and unstable["max_real"] == pytest.approx(0.255, abs=1e-3)


def test_analyse_with_params_file_and_margin(tmp_path):
    params = tmp_path / "p.yaml"
    params.write_text("Lg: 0.06\n")
    text = pisml("analyse", "--params", params, "--ug", "0.8", "--margin").stdout
    assert "STABLE" in text and "stability boundaries in ug" in text


@pytest.mark.parametrize("args, message", [
    (["data", "info", "{bad_csv}"], "row 3, column b: not a number"),
    (["data", "info", "{missing}"], "No such file or directory"),
    (["analyse", "--params", "{bad_params}", "--ug", "0.8"], "unknown parameter(s) ['Lx']"),
    (["analyse", "--ug", "-1"], "--ug must be > 0"),
    (["simulate", "--scenario", "train", "--effect-param", "current_limit.imax=abc", "--out", "{out}"],
     "current_limit: parameter imax: not a number"),
    (["simulate", "--scenario", "train", "--effect-param", "delay.order=5", "--out", "{out}"],
     "order must be 1 or 2"),
    (["identify", "--data", "{missing}", "--set", "epochs", "--out", "{out}"], "--set: 'epochs' is not KEY=VALUE"),
    (["identify", "--data", "{missing}", "--set", "epochs=0", "--out", "{out}"], "epochs must be > 0, got 0"),
])
def test_user_errors_are_one_line_with_status_2(tmp_path, args, message):
    bad_csv = tmp_path / "bad.csv"
    bad_csv.write_text("traj,t,a,b,ug,theta_g\n0,0,1,2,1,0\n0,0.0001,1,x,1,0\n")
    bad_params = tmp_path / "bad.yaml"
    bad_params.write_text("Lx: 1\n")
    fill = dict(bad_csv=bad_csv, missing=tmp_path / "nope.csv", bad_params=bad_params, out=tmp_path / "o.csv")
    proc = pisml(*[a.format(**fill) for a in args], check=False)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pisml: error: ") and message in lines[0]


def test_effects_listing():
    text = pisml("effects").stdout
    for name in ("current_limit", "current_clamp", "voltage_limit", "delay", "virtual_impedance", "param_drift",
                 "frequency_limit"):
        assert name in text


@pytest.mark.slow
def test_gap_command_names_the_hidden_limit(tmp_path):
    data = tmp_path / "hil.csv"
    pisml("simulate", "--scenario", "test", "--effect-param", "current_limit.imax=1.5", "--out", data)
    nominal = tmp_path / "nominal.yaml"
    nominal.write_text("Lf: 0.10\nCf: 0.05\n")
    proc = pisml("gap", "--data", data, "--params", nominal, "--out", tmp_path / "gap", "--quiet")
    assert "effect: current_limit" in proc.stdout
    report = json.loads((tmp_path / "gap" / "report.json").read_text())
    assert report["effects"][0]["name"] == "current_limit"
    assert report["effects"][0]["params"]["imax"] == pytest.approx(1.5, rel=0.02)
    assert report["gap_after"]["overall"] < report["gap_before"]["overall"] / 10
    assert set(report) >= {"effects", "gap_before", "gap_after", "windows", "noise_level"}
    assert {"t0", "t1", "traj", "states"} <= set(report["windows"][0])
    assert (tmp_path / "gap" / "gap.png").stat().st_size > 10_000
    augmented = json.loads((tmp_path / "gap" / "augmented_model.json").read_text())
    assert augmented["effects"]["current_limit"]["imax"] == pytest.approx(1.5, rel=0.02)


def test_gap_command_rejects_bad_references(tmp_path):
    data = tmp_path / "d.csv"
    pisml("simulate", "--scenario", "test", "--duration", "0.005", "--out", data)
    bad = tmp_path / "m.json"
    bad.write_text('{"format": "nope"}')
    proc = pisml("gap", "--data", data, "--model", bad, "--out", tmp_path / "o", check=False)
    assert proc.returncode == 2 and "field format" in proc.stderr and "Traceback" not in proc.stderr
