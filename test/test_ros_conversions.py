"""Message conversions and node-side helpers without starting nodes (fast)."""
import json
import math

import numpy as np
import pytest

pytest.importorskip("rclpy")

from pisml_ros.model import ExplicitModel, ModelFormatError  # noqa: E402
from pisml_ros.ros.conversions import (HYBRID_NOTE, failed_stability_message, message_metrics,  # noqa: E402
                                       model_from_message, model_message, overrides_from_assignments,
                                       overrides_from_fields, stability_dict)

pytestmark = pytest.mark.ros


def _model():
    return ExplicitModel(["x", "y"], ["ug", "theta_g"], ["1", "x", "ug*cos(theta_g - x)"],
                         [[0.5, 0.0], [-2.0, 1.0], [0.0, -3.0]], {"note": "test"})


def test_explicit_model_message_round_trip():
    model = _model()
    msg = model_message(model, "explicit", "m-1", {"final": 1, "loss": np.float64(0.25), "label": "text"})
    assert msg.stage == "explicit" and msg.model_id == "m-1" and msg.n_parameters == 4
    assert list(msg.terms) == model.terms and list(msg.coefficients) == [0.5, 0.0, -2.0, 1.0, 0.0, -3.0]
    assert message_metrics(msg) == {"final": 1.0, "loss": 0.25}  # non-numeric metrics are dropped
    back = model_from_message(msg)
    assert back.terms == model.terms and np.array_equal(back.coefficients, model.coefficients)
    assert msg.equations[0].startswith("d(x)/dt = 0.5")


def test_hybrid_message_has_no_model_json_and_says_why():
    class Hybrid:
        backbone = _model()
        state_names, input_names, n_parameters = ("x", "y"), ("ug", "theta_g"), 1047

    msg = model_message(Hybrid(), "hybrid", "m-2", {"trajectory": 0.1})
    assert msg.model_json == "" and not msg.terms and not msg.coefficients
    assert msg.equations[0] == HYBRID_NOTE and msg.equations[1].endswith("+ N_x(x, u)")
    assert msg.n_parameters == 1047 and message_metrics(msg)["backbone_n_parameters"] == 4
    with pytest.raises(ModelFormatError, match="model_json is empty"):
        model_from_message(msg)
    with pytest.raises(ValueError, match="stage"):
        model_message(_model(), "final", "m-3")


def test_malformed_model_json_is_a_format_error():
    msg = model_message(_model(), "explicit", "bad")
    msg.model_json = "{not json"
    with pytest.raises(ModelFormatError, match="not valid JSON"):
        model_from_message(msg)
    data = json.loads(model_message(_model(), "explicit", "bad").model_json)
    data["terms"][0] = "__import__('os').system('true')"
    msg.model_json = json.dumps(data)
    with pytest.raises(ModelFormatError, match="terms"):
        model_from_message(msg)


def test_overrides_parse_json_values_and_keep_strings():
    assert overrides_from_fields(["epochs", "refine", "hidden", "solver"], ["20", "false", "16,16", "rk4"]) == \
        {"epochs": 20, "refine": False, "hidden": "16,16", "solver": "rk4"}
    assert overrides_from_assignments(["", "epochs=3", "roles={\"angle\": \"delta\"}"]) == \
        {"epochs": 3, "roles": {"angle": "delta"}}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        overrides_from_assignments(["epochs"])
    with pytest.raises(ValueError, match="2 names but 1 values"):
        overrides_from_fields(["a", "b"], ["1"])


def test_failed_stability_report():
    msg = failed_stability_message("m", 0.3, 0.0, "no equilibrium", ["x", "y"])
    out = stability_dict(msg)
    assert out["equilibrium_found"] is False and out["stable"] is False and math.isnan(out["max_real"])
    assert out["operating_point"]["ug"] == 0.3 and out["message"] == "no equilibrium"


def test_root_locus_of_the_plant_finds_its_boundary():
    from pisml_ros.plant import InverterPlant
    from pisml_ros.analysis.margins import root_locus

    locus = root_locus(InverterPlant(), np.linspace(0.2, 1.3, 12))
    assert locus["boundaries"] == pytest.approx([1.1661], abs=1e-3)
    assert len(locus["eigenvalues"][0]) == 13 and not locus["errors"]
    assert locus["max_real"][-1] > 0 > locus["max_real"][0]


def test_analyser_warm_up_runs_the_analysis_path_without_error():
    # the node only logs a failed warm-up (it costs the first report its speed): here it must not fail
    from pisml_ros.ros.analyser import warm_up

    assert warm_up() >= 0.0


def test_demo_takes_the_reports_on_the_final_model_not_on_an_earlier_stage_of_its_run():
    from builtin_interfaces.msg import Time
    from pisml_msgs.msg import StabilityReport
    from std_msgs.msg import Header, String

    from pisml_ros.ros.demo import final_analysis

    def report(ug, sec, max_real):
        return StabilityReport(model_id="pisml-1", input_values=[ug, 0.0], max_real_part=max_real,
                               header=Header(stamp=Time(sec=sec, nanosec=0)))

    def locus(model_id, tag):
        return String(data=json.dumps({"model_id": model_id, "tag": tag}))

    # the run's first explicit model (published at 10 s) was analysed; the final one came at 100 s
    final = model_message(_model(), "explicit", "pisml-1", {"final": 1}, Time(sec=100, nanosec=5))
    arrivals = [(0, report(0.8, 11, 15.0)), (1, report(1.2, 11, 13.0))]
    loci = [(2, locus("pisml-1", "first"))]
    assert final_analysis(final, arrivals, loci) == ({}, None)
    arrivals += [(3, report(0.8, 101, -0.3)), (4, report(0.8, 100, -9.0)), (5, report(1.2, 102, -0.2))]
    reports, found = final_analysis(final, arrivals, loci)
    assert reports[0.8].max_real_part == -0.3 and reports[1.2].max_real_part == -0.2  # 100 s < 100 s + 5 ns
    assert found is None  # its root locus follows its reports
    loci += [(6, locus("other-1", "other")), (7, locus("pisml-1", "final"))]
    assert final_analysis(final, arrivals, loci)[1]["tag"] == "final"


def test_measurement_sim_source_puts_noise_on_the_inputs_only_when_asked():
    from pisml_ros.ros.measurement import load_source

    states_only = load_source("sim", "", "smallsignal", 0, 40.0, "", [""], [""])
    both = load_source("sim", "", "smallsignal", 0, 40.0, "", [""], [""], noisy_inputs=True)
    assert states_only.metadata["noise_std"]["ug"] == 0.0 and both.metadata["noise_std"]["ug"] > 0.005
    with pytest.raises(ValueError, match="parameter noisy_inputs: needs snr_db > 0"):
        load_source("sim", "", "smallsignal", 0, 0.0, "", [""], [""], noisy_inputs=True)
    # a configuration the plant cannot start from: a one-line configuration error, not a traceback
    with pytest.raises(ValueError, match="trajectory 4 starts at rest at ug0 = 1.199 p.u."):
        load_source("sim", "", "train", 0, 0.0, "", [""], ["current_limit.imax=1.5"])
