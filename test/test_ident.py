"""Identification engine: configuration, backbone, baselines, the PISML pipeline on a small problem,
metrics, and the `pisml identify` / `simulate --model` / `analyse --model` commands."""
import contextlib
import json
import math

import numpy as np
import pytest

from pisml_ros.analysis.metrics import protocol_errors, relative_error, spectrum_wasserstein, vector_relative_error
from pisml_ros.data import Dataset, Trajectory, read_dataset, write_dataset
from pisml_ros.ident import ConfigError, IdentConfig, IdentificationCancelled, SignalRoles, make_estimator
from pisml_ros.ident.backbone import fit_backbone, noise_moments, sparse_regression
from pisml_ros.ident.estimators import NO_SMALLSIGNAL_WARNING, backbone_span
from pisml_ros.ident.library import coupling_separation, physics_library
from pisml_ros.ident.selection import MAX_ALTERNATIVES
from pisml_ros.ident.trajfit import backward_elimination
from pisml_ros.model import ExplicitModel
from pisml_ros.plant import InverterPlant
from pisml_ros.plant.scenarios import generate, schedules_for
from pisml_ros.signals import INPUT_NAMES, SCORED_STATES, STATE_NAMES

from fast_config import FAST


@contextlib.contextmanager
def torch_threads(n: int):
    """torch's intra-op thread count set to ``n`` inside the block, restored after it."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def plant():
    return InverterPlant()


@pytest.fixture(scope="module")
def train(plant):
    return generate(plant, *schedules_for("train", seed=3, n_traj=4, duration=0.02))


@pytest.fixture(scope="module")
def small(plant):
    return generate(plant, *schedules_for("smallsignal", n_traj=2, duration=0.02))


@pytest.fixture(scope="module")
def test_set(plant):
    return generate(plant, *schedules_for("test"))


def test_config_rejects_unknown_and_bad_values(tmp_path):
    with pytest.raises(ConfigError, match="unknown key.*'epoch'"):
        IdentConfig.from_mapping({"epoch": 3})
    with pytest.raises(ConfigError, match="epochs must be > 0"):
        IdentConfig.from_mapping({"epochs": 0})
    with pytest.raises(ConfigError, match="refine_prune_rounds must be > 0, got 0"):
        IdentConfig.from_mapping({"refine_prune_rounds": 0})
    with pytest.raises(ConfigError, match="refine_prune_degree_preference must be >= 1, got 0.5"):
        IdentConfig.from_mapping({"refine_prune_degree_preference": 0.5})
    with pytest.raises(ConfigError, match="dropout = 'x'"):
        IdentConfig.from_mapping({"dropout": "x"})
    with pytest.raises(ConfigError, match="device must be cpu, auto or cuda.*'gpu'"):
        IdentConfig.from_mapping({"device": "gpu"})
    with pytest.raises(ConfigError, match="refine_prune_budgets must be >= 0"):
        IdentConfig.from_mapping({"refine_prune_budgets": [0.01, -1]})
    with pytest.raises(ConfigError, match="integrator_terms must be linear, error, cascade or any, got 'quadratic'"):
        IdentConfig.from_mapping({"integrator_terms": "quadratic"})
    with pytest.raises(ConfigError, match="refine_stability_points must be records or smallsignal"):
        IdentConfig.from_mapping({"refine_stability_points": "everywhere"})
    with pytest.raises(ConfigError, match="refine_stability_weight must be >= 0"):
        IdentConfig.from_mapping({"refine_stability_weight": -1})
    with pytest.raises(ConfigError, match="refine_starts must be auto, both or fallback, got 'first'"):
        IdentConfig.from_mapping({"refine_starts": "first"})
    with pytest.raises(ConfigError, match="refine_stage_prune_budget must be >= 0"):
        IdentConfig.from_mapping({"refine_stage_prune_budget": -0.1})
    with pytest.raises(ConfigError, match="refine_max_step must be >= 0"):
        IdentConfig.from_mapping({"refine_max_step": -1e-5})
    with pytest.raises(ConfigError, match="refine_max_step must be 0 .off. or at least 1e-7 s, got 1e-09"):
        IdentConfig.from_mapping({"refine_max_step": 1e-9})
    with pytest.raises(ConfigError, match="refine_rescue_ratio must be >= 0"):
        IdentConfig.from_mapping({"refine_rescue_ratio": "nan"})
    assert IdentConfig.from_mapping({"refine_rescue_ratio": "inf"}).refine_rescue_ratio == math.inf
    with pytest.raises(ConfigError, match="refine_retry_ratio must be >= 0"):
        IdentConfig.from_mapping({"refine_retry_ratio": -1})
    assert IdentConfig.from_mapping({"selection_grid_stability": "false"}).selection_grid_stability is False
    with pytest.raises(ConfigError, match="selection_round_rise must be >= 0"):
        IdentConfig.from_mapping({"selection_round_rise": "nan"})
    with pytest.raises(ConfigError, match="selection_warn_noise_ratio must be >= 0"):
        IdentConfig.from_mapping({"selection_warn_noise_ratio": "nan"})
    with pytest.raises(ConfigError, match="selection_round_rise must be >= 0"):
        IdentConfig.from_mapping({"selection_round_rise": -0.1})
    with pytest.raises(ConfigError, match="clean_growing_error must be >= 0"):
        IdentConfig.from_mapping({"clean_growing_error": -0.1})
    assert IdentConfig.from_mapping({"clean_growing_error": "inf"}).clean_growing_error == math.inf
    with pytest.raises(ConfigError, match="refine_single_precision_stages must be >= 0"):
        IdentConfig.from_mapping({"refine_single_precision_stages": -1})
    for bad in ("240,0", "240.5,0,0", "-1,0,0"):
        with pytest.raises(ConfigError, match="refine_growing_max_windows must be empty or one count >= 0"):
            IdentConfig.from_mapping({"refine_growing_max_windows": bad})
    assert IdentConfig.from_mapping({"refine_growing_max_windows": "240,0,0"}).refine_growing_max_windows == (240, 0, 0)
    cfg = IdentConfig.from_mapping({"epochs": "7", "hidden": "32,16", "refine": "false",
                                    "refine_prune_budgets": "0.002,0.02"})
    assert cfg.epochs == 7 and cfg.hidden == (32, 16) and cfg.refine is False
    assert cfg.refine_prune_budgets == (0.002, 0.02)
    path = tmp_path / "ident.yaml"
    path.write_text("identification:\n  epochs: 9\n  roles:\n    angle: delta\n")
    assert IdentConfig.load(path, {"window": 5}).epochs == 9
    path.write_text("identification:\n  roles:\n    angel: delta\n")
    with pytest.raises(ValueError, match="unknown key"):
        IdentConfig.load(path)


def test_settings_from_assignments_keep_strings_and_name_a_malformed_item():
    from pisml_ros.ident import settings_from_assignments

    assert settings_from_assignments([" epochs = 3", "", "roles={\"angle\": \"d\"}", "hidden=16,16"]) == {
        "epochs": "3", "roles": '{"angle": "d"}', "hidden": "16,16"}
    # IdentConfig converts the strings as it does a file's values
    assert IdentConfig.load(None, settings_from_assignments(["epochs=3", "hidden=16,16"])).hidden == (16, 16)
    with pytest.raises(ConfigError, match="overrides: 'epochs' is not KEY=VALUE"):
        settings_from_assignments(["epochs"], "overrides")


def test_physics_library_follows_the_roles():
    roles = SignalRoles.from_mapping({"frequency": "Pf"})
    terms = physics_library(roles, ("delta", "Pf", "Qf", "phi_d", "phi_q", "gamma_d", "gamma_q", "il_d", "il_q",
                                    "vc_d", "vc_q", "ig_d", "ig_q"))
    # rotating-frame couplings: the frequency state times every dq voltage and current
    assert {"Pf*vc_d", "Pf*vc_q", "Pf*ig_d", "Pf*ig_q", "Pf*il_d", "Pf*il_q"} <= set(terms)
    assert "vc_d*ig_d + vc_q*ig_q" in terms and "ug*sin(theta_g - delta)" in terms
    other = SignalRoles.from_mapping({"frequency": "w_pll", "voltage": ["v_a", "v_b"], "current": ["i_a", "i_b"],
                                      "other_currents": []})
    assert [t for t in physics_library(other, ("w_pll", "v_a")) if t.startswith("w_pll*")] == [
        "w_pll*v_a", "w_pll*v_b", "w_pll*i_a", "w_pll*i_b"]
    no_coupling = SignalRoles.from_mapping({"frequency": None})
    assert not any(t.startswith("Pf*") for t in physics_library(no_coupling, ("Pf", "vc_d")))
    with pytest.raises(ValueError, match="w_pll"):
        other.check(["v_a", "v_b", "i_a", "i_b"], ["ug", "theta_g"])


def test_backbone_is_fast_sparse_and_close(train, test_set):
    terms = physics_library(IdentConfig().roles, train.state_names)
    model = fit_backbone(train, terms, threshold=0.02)
    assert model.n_parameters < len(terms) * 13
    # Θ cannot hold the vo = vc + Rd(il - ig) products, and 4 short records are little data:
    # a few per cent in distribution, not more
    assert protocol_errors(model, test_set)["iod"] < 10
    # out of distribution (a sag to 0.4 moves the frequency far), 4 records of 20 ms do not pin the
    # frequency couplings apart from the plain states; without them the backbone extrapolates
    plain = fit_backbone(train, physics_library(IdentConfig().roles, train.state_names, coupling=False),
                         threshold=0.02)
    errs = protocol_errors(plain, test_set)
    assert errs["iod"] < 10 and errs["ood"] < 10
    assert set(errs) == {"iod", "ood", "iod_vector", "ood_vector"} and all(map(math.isfinite, errs.values()))


def test_backbone_window_is_bounded_in_time_at_coarse_sampling():
    config = IdentConfig()
    assert (config.backbone_span, config.backbone_span_max_s) == (10, 0.001)
    # the protocol's 10 kHz: 10 samples either way; 5 kHz: the same 1 ms in 5; 20 kHz: 10 samples, 0.5 ms
    assert [backbone_span(config, dt) for dt in (1e-4, 2e-4, 5e-5, 1 / 3000, 1e-3)] == [10, 5, 10, 3, 3]
    unbounded = IdentConfig.from_mapping({"backbone_span_max_s": 0.0})
    assert backbone_span(unbounded, 2e-4) == 10
    assert backbone_span(IdentConfig.from_mapping({"backbone_span": 4}), 1e-4) == 4
    assert backbone_span(IdentConfig.from_mapping({"backbone_span": 2}), 1e-3) == 2  # the bound never lengthens
    with pytest.raises(ConfigError, match="backbone_span_max_s must be >= 0, got -0.001"):
        IdentConfig.from_mapping({"backbone_span_max_s": -0.001})


def test_noise_compensated_regression_removes_the_errors_in_variables_bias():
    # b = 2 x + 0.5 y with x and y measured with noise as large as x's own spread: plain least
    # squares attenuates the x coefficient towards 2 / (1 + 1) = 1; the compensated fit does not
    rng = np.random.default_rng(0)
    n = 20000
    x, y = rng.standard_normal(n), rng.standard_normal(n)
    b = (2 * x + 0.5 * y)[:, None]
    a = np.column_stack([x + rng.standard_normal(n), y + 0.1 * rng.standard_normal(n)])
    noise_aa = np.diag([1.0, 0.01]) * n
    plain = sparse_regression(a, b, 0.0, 1e-9)
    compensated = sparse_regression(a, b, 0.0, 1e-9, noise_aa=noise_aa, noise_ab=np.zeros((2, 1)))
    assert abs(plain[0, 0] - 1.0) < 0.05
    assert abs(compensated[0, 0] - 2.0) < 0.1 and abs(compensated[1, 0] - 0.5) < 0.05


def test_noise_moments_match_the_noise_level(train):
    from pisml_ros.model.expressions import term_set
    from pisml_ros.plant.noise import add_measurement_noise

    noisy = add_measurement_noise(train, 40.0, seed=1)
    terms = term_set(["1", "il_d"], tuple(train.state_names) + tuple(train.input_names))
    sigma = np.full(len(train.state_names), 0.01)
    noise_aa, noise_ab = noise_moments(noisy, terms, 10, sigma, draws=16)
    # the trapezoid integral of white noise over 10 samples: variance σ²·dt²·Σ(weights²)
    rows = sum(len(tr) - 10 for tr in train)
    weights = np.r_[0.5, np.ones(9), 0.5]
    expected = rows * 0.01 ** 2 * train.dt ** 2 * np.sum(weights ** 2)
    assert noise_aa[0, 0] == pytest.approx(0.0, abs=1e-18)
    assert noise_aa[1, 1] == pytest.approx(expected, rel=0.1)
    # the end points shared by the integral and the increment n_end − n_start carry equal weights
    # (0.5·dt), so their correlations cancel
    il = train.state_names.index("il_d")
    assert abs(noise_ab[1, il]) < 0.1 * np.sqrt(noise_aa[1, 1] * rows * 2 * 0.01 ** 2)


def test_backward_elimination_drops_collinear_spurious_terms():
    # y = 2 a0 - a2 + 3 a5; a1, a3, a4 are near copies of the true columns plus a little noise
    rng = np.random.default_rng(4)
    base = rng.standard_normal((400, 3))
    a = np.column_stack([base[:, 0], base[:, 0] + 0.05 * rng.standard_normal(400), base[:, 1],
                         base[:, 1] + base[:, 2] + 0.05 * rng.standard_normal(400),
                         0.3 * rng.standard_normal(400), base[:, 2]])
    y = a @ np.array([2.0, 0, -1.0, 0, 0, 3.0]) + 1e-3 * rng.standard_normal(400)
    full = np.linalg.lstsq(a, y, rcond=None)[0][:, None]
    cost = 0.5 * np.sum((a @ full[:, 0] - y) ** 2)
    small, large = backward_elimination(full, a.T @ a, np.arange(6), [0.5 * cost, 1e9 * cost])
    rise, coef = small
    assert np.flatnonzero(coef[:, 0]).tolist() == [0, 2, 5]
    # the kept coefficients are the least-squares refit on that support (exact for a quadratic cost)
    refit = np.linalg.lstsq(a[:, [0, 2, 5]], y, rcond=None)[0]
    np.testing.assert_allclose(coef[[0, 2, 5], 0], refit, rtol=1e-8)
    np.testing.assert_allclose(rise, 0.5 * np.sum((a[:, [0, 2, 5]] @ refit - y) ** 2) - cost, rtol=1e-6)
    assert np.count_nonzero(large[1]) < 3


def test_backward_elimination_keeps_the_last_term_of_each_group():
    # two equations over terms a0, a1: y0 = 2 a0 + a1, y1 = 1e-3 a1 (a state whose equation the data
    # hardly ask for, like an integrator of a regulated error): by cost alone its only term goes
    # first; with the equations as groups it stays, and only equation 0 loses a term
    rng = np.random.default_rng(5)
    a = rng.standard_normal((300, 2))
    coef = np.array([[2.0, 0.0], [1.0, 1e-3]])  # (terms, equations): the least-squares fit
    support = np.array([0, 2, 3])  # flat (term, equation): a0 in eq 0, a1 in eq 0, a1 in eq 1
    block = a.T @ a
    hessian = np.zeros((3, 3))
    hessian[:2, :2], hessian[2, 2] = block, block[1, 1]
    (_, plain), = backward_elimination(coef, hessian, support, [1e12])
    (_, grouped), = backward_elimination(coef, hessian, support, [1e12], groups=support % 2)
    assert not plain[:, 1].any()
    assert np.count_nonzero(grouped[:, 0]) == 1 and grouped[1, 1] == pytest.approx(1e-3)
    # within a small budget the groups change nothing
    tiny = 0.5 * 1e-6 * block[1, 1] * 0.5
    (_, a_plain), = backward_elimination(coef, hessian, support, [tiny])
    (_, a_grouped), = backward_elimination(coef, hessian, support, [tiny], groups=support % 2)
    np.testing.assert_array_equal(a_plain, a_grouped)
    assert np.count_nonzero(a_plain) == 3


def test_backward_elimination_keeps_a_coefficient_whose_drop_leaves_a_mode_that_does_not_pull_back():
    # x' = -x, z' = 0.5 x - 0.5 z, where the data hardly see z's own pull (a Hessian of 1e-2 on it):
    # by cost it goes first and leaves z' = 0.5 x, a zero mode (stop 75's recording 4 at 40 dB lost
    # the pull on Qf so). With the terms' gradients at a rest state the drop is refused; a start
    # that has such a mode already is not judged
    coef = np.array([[-1.0, 0.5], [0.0, -0.5]])  # (terms x, z; equations x, z)
    support = np.array([0, 1, 3])  # x in eq x, x in eq z, z in eq z
    hessian = np.diag([1e4, 1e4, 1e-2])
    gradients = [np.eye(2)]  # terms x, z in states x, z
    (_, plain), = backward_elimination(coef, hessian, support, [1.0], groups=support % 2)
    assert plain[1, 1] == 0.0
    (_, kept), = backward_elimination(coef, hessian, support, [1.0], groups=support % 2,
                                      state_gradients=gradients, zero_mode=0.01)
    np.testing.assert_array_equal(kept, coef)
    (_, off), = backward_elimination(coef, hessian, support, [1.0], groups=support % 2,
                                     state_gradients=gradients, zero_mode=0.0)
    np.testing.assert_array_equal(off, plain)
    # a mode that passes near zero at one point only (a slow mode crossing as terms go) is no lost
    # pull: z' = 0.5 x - 0.5 z + x z without its -0.5 z has z's rate x, zero at x = 0 alone
    bilinear = np.array([[-1.0, 0.5], [0.0, -0.5], [0.0, 1.0]])  # terms x, z, x*z
    at_x0, at_x1 = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]]), np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    support3, hessian3 = np.array([0, 1, 3, 5]), np.diag([1e4, 1e4, 1e-2, 1e4])
    (_, one), = backward_elimination(bilinear, hessian3, support3, [1.0], groups=support3 % 2,
                                     state_gradients=[at_x0], zero_mode=0.01)
    (_, both), = backward_elimination(bilinear, hessian3, support3, [1.0], groups=support3 % 2,
                                      state_gradients=[at_x0, at_x1], zero_mode=0.01)
    assert one[1, 1] == -0.5 and both[1, 1] == 0.0
    slow = coef.copy()
    slow[1, 1] = -1e-3  # a mode at 1e-3 1/s from the start
    (_, dropped), = backward_elimination(slow, hessian, support, [1.0], groups=support % 2,
                                         state_gradients=gradients, zero_mode=0.01)
    assert dropped[1, 1] == 0.0
    assert IdentConfig().refine_prune_zero_mode == 0.01  # (the default since stop 76)
    with pytest.raises(ConfigError, match="refine_prune_zero_mode"):
        IdentConfig.from_mapping({"refine_prune_zero_mode": -1})


def test_order_weights_choose_which_of_two_stand_ins_goes_and_the_budget_counts_true_rises():
    # a1 is a near copy of a0 that the data favour a little (y leans on a1): by cost alone a0 goes;
    # with a1 weighted as the higher-degree term (rises ranked at 1/10), a1 goes and a0 carries y
    rng = np.random.default_rng(7)
    x = rng.standard_normal(500)
    a = np.column_stack([x, x + 0.02 * rng.standard_normal(500), rng.standard_normal(500)])
    y = a @ np.array([1.0, 1.5, 1.0]) + 1e-3 * rng.standard_normal(500)
    full = np.linalg.lstsq(a, y, rcond=None)[0][:, None]
    cost = 0.5 * np.sum((a @ full[:, 0] - y) ** 2)
    rise_a0 = 0.5 * np.sum((a[:, 1:] @ np.linalg.lstsq(a[:, 1:], y, rcond=None)[0] - y) ** 2) - cost
    rise_a1 = 0.5 * np.sum((a[:, [0, 2]] @ np.linalg.lstsq(a[:, [0, 2]], y, rcond=None)[0] - y) ** 2) - cost
    assert rise_a0 < rise_a1 < 5 * rise_a0
    budget = 1.01 * rise_a1  # room for one removal, not for two
    (_, plain), = backward_elimination(full, a.T @ a, np.arange(3), [budget])
    (rise, weighted), = backward_elimination(full, a.T @ a, np.arange(3), [budget], order_weights=np.array([1, 0.1, 1]))
    assert np.flatnonzero(plain[:, 0]).tolist() == [1, 2]
    assert np.flatnonzero(weighted[:, 0]).tolist() == [0, 2]
    assert rise == pytest.approx(rise_a1, rel=1e-6)
    # a weight that makes a removal look cheap does not stretch the budget
    (_, tight), = backward_elimination(full, a.T @ a, np.arange(3), [0.99 * rise_a1], order_weights=np.array([1, 0.1, 1]))
    assert np.flatnonzero(tight[:, 0]).tolist() == [0, 1, 2]


def test_term_degrees_count_factors():
    from pisml_ros.ident.library import term_degrees

    terms = ["1", "il_d", "cos(delta)", "Pf*il_d", "vc_d**2", "ug*cos(delta - theta_g)", "il_d/(1 + il_d**2)",
             "ig_d*il_d*vc_q"]
    assert term_degrees(terms, STATE_NAMES + INPUT_NAMES).tolist() == [1, 1, 1, 2, 2, 2, 2, 3]


def test_couplings_are_kept_only_where_the_data_separate_them(plant, train):
    roles = IdentConfig().roles
    assert roles.frequency == "Pf"
    x_small = np.concatenate([tr.x for tr in train])
    # 4 records of 20 ms: Pf hardly leaves P*, so Pf*s is nearly an affine function of s
    assert coupling_separation(x_small, train.state_names, roles) < IdentConfig().coupling_min_separation
    protocol = generate(plant, *schedules_for("train", seed=0))
    x_big = np.concatenate([tr.x for tr in protocol])
    assert coupling_separation(x_big, protocol.state_names, roles) > 0.3
    assert coupling_separation(x_big, protocol.state_names, SignalRoles.from_mapping({"frequency": None})) == 0.0
    # the estimator records its decision and builds Θ accordingly
    est = make_estimator("pisml", IdentConfig.from_mapping({**FAST, "refine": False})).fit(train)
    assert est.metrics_["frequency_couplings"] == 0.0
    assert not any(t.startswith("Pf*") for t in est.backbone_.terms)
    assert est.backbone_.metadata["frequency_couplings"]["used"] is False
    assert est.backbone_.metadata["backbone_span_samples"] == 10  # 1 ms at the records' 10 kHz
    forced = IdentConfig.from_mapping({**FAST, "refine": False, "coupling_min_separation": 0.0})
    est = make_estimator("pisml", forced).fit(train)
    assert any(t.startswith("Pf*") for t in est.backbone_.terms)


@pytest.mark.parametrize("method", ["mod-sindy", "std-sindy"])
def test_sindy_baselines_give_rebuildable_explicit_models(method, train, tmp_path):
    est = make_estimator(method).fit(train)
    assert est.explicit_model_ is est.model_
    path = est.explicit_model_.save(tmp_path / "m.json")
    again = ExplicitModel.load(path)
    x, u = train.trajectories[0].x[:5], train.trajectories[0].u[:5]
    np.testing.assert_allclose(again.vector_field(x, u), est.model_.vector_field(x, u), rtol=1e-10, atol=1e-8)
    assert est.metrics_["n_parameters"] == est.model_.n_parameters


def test_pisml_pipeline_stages_and_model(train, small, test_set):
    updates = []
    est = make_estimator("pisml", IdentConfig.from_mapping(FAST)).fit(train, small, callback=updates.append)
    stages = [u.stage for u in updates if u.model is not None]
    # the best explicit model so far goes out before the (long) refinement, the selected one at the end
    assert stages == ["backbone", "hybrid", "explicit (before refinement)", "explicit"]
    preliminary = next(u.model for u in updates if u.stage == "explicit (before refinement)")
    assert isinstance(preliminary, ExplicitModel)
    assert preliminary.metadata["selection"]["chosen"] in ("backbone", "trained backbone", "distilled",
                                                           *[n for n in est.candidates_ if n.startswith("re-fit")])
    assert {f"re-fit +{b:g} %" for b in (100, 300, 1000)} <= set(est.candidates_)
    progress = [u.progress for u in updates]
    assert progress == sorted(progress) and progress[-1] == 1.0
    model = est.explicit_model_
    assert isinstance(model, ExplicitModel) and model.metadata["stage"] == "explicit"
    # candidates are scored on the small-signal records too, and every one's consistency with the
    # records' rest points is on record
    selection = model.metadata["selection"]
    assert selection["scored_on"] == "training and small-signal records"
    assert set(selection["inconsistent_rest_points"]) <= set(est.candidates_)
    # ... the small-signal records' rest point among them (the consistency check's points)
    assert any(np.allclose(p["inputs"], small.trajectories[0].u[0]) for p in model.metadata["reference_points"])
    # hybrid training moves Ξ on the backbone's support and never re-opens the zeros STLSQ left
    trained = est.candidates_["trained backbone"].coefficients
    assert np.array_equal(trained != 0, est.backbone_.coefficients != 0)
    assert not np.allclose(trained, est.backbone_.coefficients)
    assert est.hybrid_.n_parameters > 10 * model.n_parameters
    # the merged model uses products that Θ alone does not have
    assert any("*" in t and "+" not in t and "cos" not in t for t in model.terms)
    # JSON round trip rebuilds the same field
    again = ExplicitModel.from_dict(json.loads(model.to_json()))
    x, u = train.trajectories[1].x[:3], train.trajectories[1].u[:3]
    np.testing.assert_allclose(again.vector_field(x, u), model.vector_field(x, u), rtol=1e-12)
    # ... and the candidates that fitted about as well (the selection's tolerance), each its own field
    assert len(again.alternatives()) <= MAX_ALTERNATIVES
    for name, alternative in again.alternatives():
        assert name != selection["chosen"] and np.isfinite(selection["training_error_pct"][name])
        np.testing.assert_allclose(alternative.vector_field(x, u), est.candidates_[name].vector_field(x, u), rtol=1e-12)
    errs = protocol_errors(model, test_set)
    assert errs["iod"] < 10 and errs["ood"] < 10
    eig = model.eigenvalues(0.8, 0.0)
    assert eig.shape == (13,) and np.all(np.isfinite(eig))
    # a candidate reproduces these clean records within clean_growing_error: no growing-window fallback
    assert min(selection["training_error_pct"].values()) < IdentConfig().clean_growing_error
    assert "refinement_growing_fallback" not in model.metadata
    assert not any(name.endswith("from distilled") for name in est.candidates_)
    # every fit searches its records for a limit of a reference (stop 56): this plant has none
    assert model.metadata["limiter"]["run"] and not model.metadata["limiter"]["found"]
    assert not model.metadata["limiter"]["family"] and not any("with limit" in name for name in est.candidates_)


def test_clean_records_no_candidate_reproduces_are_refined_in_growing_windows_from_the_merged_model(train, small,
                                                                                                   monkeypatch):
    # with clean_growing_error 0 no candidate is good enough: the merged model is refined as noisy
    # records are (coarse samples leave the equation-error starts wrong, IdentConfig.clean_growing_error)
    updates = []
    est = make_estimator("pisml", IdentConfig.from_mapping({**FAST, "clean_growing_error": 0.0})).fit(
        train, small, callback=updates.append)
    progress = [u.progress for u in updates]
    assert progress == sorted(progress) and progress[-1] == 1.0
    refined = est.candidates_["refined from distilled"]
    assert refined.metadata["refinement"]["start"] == "distilled"
    assert refined.metadata["refinement"]["growing_windows"]["windows"] == list(IdentConfig().refine_growing_windows)
    assert "pruned +0.1 % from distilled" in est.candidates_
    selection = est.explicit_model_.metadata["selection"]
    fallback = est.explicit_model_.metadata["refinement_growing_fallback"]
    # what the selection would have taken without it, and the family it added
    assert not fallback["selected_before"].endswith("from distilled")
    assert fallback["error_pct"] == selection["training_error_pct"][fallback["selected_before"]]
    assert fallback["added"] == sorted(name for name in est.candidates_ if name.endswith("from distilled"))
    assert est.metrics_["clean_growing_fallback"] == 1.0
    # the family competes: scored with the others
    assert {"refined from distilled", "pruned +0.1 % from distilled"} <= set(selection["training_error_pct"])
    # noisy records are refined in growing windows anyway: no fallback on top
    from pisml_ros.plant.noise import add_measurement_noise

    # (refine_rescue_ratio and refine_retry_ratio 0: the rescue of noisy fits and the second start
    # after it always run here, tested below; refine_starts fallback with the first start's family
    # taken as sufficient and its refinement as not lost (FAST settings can lose it), so that the
    # second start is skipped and comes after the rescue)
    from pisml_ros.ident import estimators

    monkeypatch.setattr(estimators, "_refinement_suffices", lambda *args, **kwargs: True)
    monkeypatch.setattr(estimators, "_unpruned_refinement_lost", lambda *args, **kwargs: False)
    updates.clear()
    noisy = make_estimator("pisml", IdentConfig.from_mapping(
        {**FAST, "clean_growing_error": 0.0, "refine_rescue_ratio": 0.0, "refine_retry_ratio": 0.0,
         "refine_starts": "fallback"})).fit(
        add_measurement_noise(train, 40.0, seed=1), add_measurement_noise(small, 40.0, seed=2),
        callback=updates.append)
    progress = [u.progress for u in updates]
    assert progress == sorted(progress) and progress[-1] == 1.0
    assert "refinement_growing_fallback" not in noisy.explicit_model_.metadata
    assert not any(name.endswith("from distilled") for name in noisy.candidates_)
    # the rescue of a noisy fit: the first start refined again with the stability prior in the
    # growing-window stages, a family of its own that competes in the selection
    rescue = noisy.explicit_model_.metadata["refinement_rescue"]
    scored = noisy.explicit_model_.metadata["selection"]["training_error_pct"]
    assert rescue["run"] and rescue["ratio"] == pytest.approx(rescue["error_pct"] / rescue["noise_floor_pct"])
    # the selection records the same floor, for its warning on a model far worse than the noise
    assert noisy.explicit_model_.metadata["selection"]["noise_floor_pct"] == pytest.approx(rescue["noise_floor_pct"])
    # a family of its own: its pruned models are judged against its own refined model
    from pisml_ros.ident.selection import _refinement_family

    assert {_refinement_family(name) for name in rescue["added"]} == {" with growing prior",
                                                                      " at long windows with growing prior"}
    assert rescue["added"] == sorted(name for name in noisy.candidates_ if name.endswith(" with growing prior"))
    assert "refined with growing prior" in rescue["added"] and set(rescue["added"]) <= set(scored)
    weight = IdentConfig().refine_rescue_stability_weight
    prior = noisy.candidates_["refined with growing prior"].metadata["refinement"]
    assert prior["growing_windows"]["stability_weight"] == weight > 0
    assert noisy.candidates_["refined"].metadata["refinement"]["growing_windows"]["stability_weight"] == 0
    assert prior["start"] == noisy.candidates_["refined"].metadata["refinement"]["start"]
    assert noisy.metrics_["refinement_rescue"] == 1.0
    # still above refine_retry_ratio after the rescue (0 here: always): the second start, skipped
    # after the first start's family, is refined too and its family competes
    second = noisy.explicit_model_.metadata["refinement_second_start"]
    assert rescue["ratio_after"] > 0 and second["run"] and second["after_rescue"]
    assert f"refined from {second['start']}" in noisy.candidates_
    assert f"refined from {second['start']}" in scored and noisy.metrics_["refinement_starts_run"] == 2.0


def test_noise_floor_error_is_what_the_noise_alone_leaves(train, small):
    # a model reproducing the noise-free states exactly scores the noise floor against noisy records
    from pisml_ros.data.dataset import concat_datasets
    from pisml_ros.ident.noise import noise_floor_error
    from pisml_ros.plant.noise import add_measurement_noise

    clean = concat_datasets([train, small])
    for snr in (40.0, 30.0):
        noisy = add_measurement_noise(clean, snr, seed=4)
        exact = np.mean([relative_error(c.x, n.x) for c, n in zip(clean, noisy)])
        assert noise_floor_error(noisy) == pytest.approx(exact, rel=0.15)
    assert noise_floor_error(clean) < 1e-3 * noise_floor_error(add_measurement_noise(clean, 40.0, seed=4))


def test_the_estimated_snr_is_the_one_the_noise_was_drawn_at_whatever_the_records_operating_points(train):
    # the noise floor weighs each record by its own norm; the SNR is the records' together, as drawn
    import dataclasses

    from pisml_ros.data import Dataset
    from pisml_ros.ident.noise import estimated_snr_db, noise_floor_error
    from pisml_ros.plant.noise import add_measurement_noise

    for snr in (40.0, 35.0, 30.0):
        assert estimated_snr_db(add_measurement_noise(train, snr, seed=5)) == pytest.approx(snr, abs=0.5)
    assert estimated_snr_db(train) == np.inf
    # records at a quarter of the states' size beside full-size ones: the floor rises, the SNR holds
    scaled = [dataclasses.replace(tr, x=tr.x * (0.25 if k % 2 else 1.0)) for k, tr in enumerate(train)]
    mixed = add_measurement_noise(Dataset(train.state_names, train.input_names, scaled, dict(train.metadata)),
                                  40.0, seed=5)
    alike = add_measurement_noise(train, 40.0, seed=5)
    assert noise_floor_error(mixed) > 1.5 * noise_floor_error(alike)
    assert estimated_snr_db(mixed) == pytest.approx(40.0, abs=0.5)
    # every fit's model records it (clean: None, as JSON has no inf)
    from pisml_ros.ident.estimators import _meta

    assert _meta("pisml", IdentConfig(), alike, None)["training"]["estimated_snr_db"] == pytest.approx(40.0, abs=0.5)
    assert json.loads(json.dumps(_meta("pisml", IdentConfig(), train, None)))["training"]["estimated_snr_db"] is None


def test_noisy_measured_inputs_are_held_at_their_means_where_they_are_constant(train, small):
    from pisml_ros.data.dataset import concat_datasets
    from pisml_ros.ident.noise import input_noise_std, piecewise_constant_inputs
    from pisml_ros.plant.noise import add_measurement_noise

    clean = concat_datasets([train, small])
    # inputs applied as exact steps have no noise to remove: nothing changes
    assert np.array_equal(input_noise_std(clean), np.zeros(2))
    noisy = add_measurement_noise(clean, 40.0, seed=5, include_inputs=True)
    quieter = add_measurement_noise(clean, 40.0, seed=5, include_inputs=True, input_snr_db=60.0)
    assert quieter.metadata["noise_std"]["ug"] == pytest.approx(0.1 * noisy.metadata["noise_std"]["ug"])
    assert quieter.metadata["noise_std"]["ig_d"] == noisy.metadata["noise_std"]["ig_d"]
    sigma = input_noise_std(noisy)
    true = np.array([noisy.metadata["noise_std"][name] for name in noisy.input_names])
    assert sigma == pytest.approx(true, rel=0.15)
    held, report = piecewise_constant_inputs(noisy)
    error = np.concatenate([h.u - c.u for h, c in zip(held, clean)])
    raw = np.concatenate([n.u - c.u for n, c in zip(noisy, clean)])
    # every step found (the small-signal records' 0.01 p.u. step is about 1 sigma of this noise),
    # the noise left a fraction of what it was; the states untouched
    assert report["ug"]["samples"] > 0.95 * clean.n_samples and report["ug"]["sigma"] == pytest.approx(sigma[0])
    assert np.all(error.std(axis=0) < 0.3 * raw.std(axis=0))
    assert all(np.array_equal(h.x, n.x) for h, n in zip(held, noisy))
    assert held.metadata["inputs_denoised"] == {"ug": sigma[0], "theta_g": sigma[1]}
    # an input that is not constant between changes (an oscillation, a ramp) is mostly left as
    # measured, and what is held stays within its noise (measured: 0.00106 and 0.00115 against 0.0010)
    t = noisy.trajectories[0].t
    true = np.column_stack([1.0 + 0.05 * np.sin(2 * np.pi * 50 * t), 0.3 * t / t[-1]])
    measured = true + 0.001 * np.random.default_rng(0).standard_normal(true.shape)
    swinging = Dataset(noisy.state_names, noisy.input_names, [Trajectory(0, t, noisy.trajectories[0].x, measured)])
    swung, report = piecewise_constant_inputs(swinging, sigma=[0.001, 0.001])
    assert report["ug"]["samples"] < 0.3 * len(t) and report["theta_g"]["samples"] < 0.3 * len(t)
    assert np.all((swung.trajectories[0].u - true).std(axis=0) < 1.25 * (measured - true).std(axis=0))


def test_held_levels_are_pooled_where_a_record_returns_and_where_every_record_starts():
    # the 50 samples before a small-signal step hold its level to sigma/7; the records that stay at
    # that operating point hold it to sigma/22: pooled, the step's records take the common level
    from pisml_ros.ident.noise import piecewise_constant_inputs

    rng = np.random.default_rng(3)
    sigma = 0.008

    def dataset(levels_per_record):
        records = []
        for k, levels in enumerate(levels_per_record):
            u_true = np.concatenate([np.full(n, level) for level, n in levels])
            t = np.arange(len(u_true)) * 1e-4
            measured = np.column_stack([u_true + sigma * rng.standard_normal(len(t)), np.zeros(len(t))])
            records.append((Trajectory(k, t, np.zeros((len(t), 1)), measured), u_true))
        return Dataset(("x",), ("ug", "theta_g"), [r for r, _ in records]), [u for _, u in records]

    small, truth = dataset([[(0.8, 50), (0.81, 950)], [(0.8, 50), (0.79, 950)], [(0.8, 1000)], [(0.8, 1000)]])
    held, report = piecewise_constant_inputs(small, sigma=[sigma, 0.0])
    common = held.trajectories[3].u[0, 0]
    assert all(tr.u[0, 0] == common for tr in held)
    at_common = np.concatenate([tr.u[:, 0] == common for tr in held])
    # one level over the ~2100 samples there (a step of ~1 sigma is found within a few samples)
    assert abs(at_common.sum() - 2100) <= 12
    assert common == pytest.approx(np.concatenate([tr.u[:, 0] for tr in small])[at_common].mean())
    assert held.trajectories[0].u[60, 0] != common and abs(held.trajectories[0].u[60, 0] - 0.81) < 0.001
    assert report["ug"]["pooled"] == 4 and report["theta_g"]["pooled"] == 0
    assert abs(common - 0.8) < 3 * sigma / np.sqrt(2100)
    unpooled, _ = piecewise_constant_inputs(small, sigma=[sigma, 0.0], pool_threshold=0.0)
    alone = unpooled.trajectories[0].u[:, 0]
    assert alone[0] != common and alone[0] == pytest.approx(small.trajectories[0].u[alone == alone[0], 0].mean())
    # a sag and its recovery share a level; records that start at different levels are not pooled
    # across, even where two of their levels lie within the test's reach of each other
    sags, truth = dataset([[(1.0, 150), (0.9, 150), (1.0, 30)], [(1.002, 200), (0.95, 130)]])
    held, report = piecewise_constant_inputs(sags, sigma=[sigma, 0.0])
    first = held.trajectories[0].u[:, 0]
    assert first[0] == first[-1] and abs(np.sum(first == first[0]) - 180) <= 12
    assert held.trajectories[1].u[0, 0] != first[0] and np.sum(held.trajectories[1].u[:, 0] == first[0]) == 0
    assert report["ug"]["pooled"] == 2


def test_shallow_sags_are_found_and_uncertain_steps_take_their_posterior_mean():
    # a sag of ~1 sigma over 90 of 400 samples: one split sees it diluted (under 5 standard errors),
    # the inner interval's test at ~9; a step of 1.5 sigma is placed only to a few samples, so the
    # samples around it take m1 + (m2 - m1) P(step <= k), and a step of 20 sigma stays where it is
    from pisml_ros.ident.noise import _mean_shift_segments, _soft_edges, piecewise_constant_inputs

    rng = np.random.default_rng(9)
    sigma = 0.01
    u_true = np.concatenate([np.full(70, 1.0), np.full(90, 0.99), np.full(240, 1.0)])
    measured = u_true + sigma * rng.standard_normal(400)
    assert _mean_shift_segments(measured, sigma, 6.0) == [(0, 400)]
    spans = _mean_shift_segments(measured, sigma, 6.0, interval_threshold=6.0)
    assert len(spans) == 3 and abs(spans[1][0] - 70) <= 6 and abs(spans[1][1] - 160) <= 6
    pure = sigma * rng.standard_normal((20, 400))
    assert all(len(_mean_shift_segments(row, sigma, 6.0, interval_threshold=6.0)) == 1 for row in pure)
    # the posterior mean around a small step: monotone between the levels, each sample's expected value
    step = np.concatenate([np.full(100, 0.8), np.full(100, 0.815)])
    noisy = step + sigma * rng.standard_normal(200)
    held = np.concatenate([np.full(100, 0.8), np.full(100, 0.815)])
    soft = _soft_edges(noisy, held, [(0, 100, 200)], sigma, 25)
    assert np.all(np.diff(soft) >= 0) and soft[0] == 0.8 and soft[-1] == 0.815
    assert np.all(soft[:75] == 0.8) and np.all(soft[125:] == 0.815)
    assert 0 < np.sum((soft > 0.8) & (soft < 0.815)) <= 50
    big = np.concatenate([np.full(100, 0.8), np.full(100, 1.0)])
    kept = _soft_edges(big + sigma * rng.standard_normal(200), big, [(0, 100, 200)], sigma, 25)
    np.testing.assert_array_equal(kept, big)
    # in piecewise_constant_inputs: the sag found, its edges softened, the levels outside them kept exactly
    record = Trajectory(0, np.arange(400) * 1e-4, np.zeros((400, 1)), np.column_stack([measured, np.zeros(400)]))
    data = Dataset(("x",), ("ug", "theta_g"), [record])
    plain, _ = piecewise_constant_inputs(data, sigma=[sigma, 0.0])
    assert np.unique(plain.trajectories[0].u[:, 0]).size == 1
    found, report = piecewise_constant_inputs(data, sigma=[sigma, 0.0], interval_threshold=6.0, edge_width=25)
    u = found.trajectories[0].u[:, 0]
    assert report["ug"]["replaced"] == 3 and u[0] == u[-1] and abs(u[115] - 0.99) < 0.003
    assert np.mean(np.abs(u - u_true)) < np.mean(np.abs(plain.trajectories[0].u[:, 0] - u_true))


def test_small_signal_residuals_profile_out_the_held_levels_errors():
    # the response is linear in the step: the profiled levels recover a held level's error from
    # the deviations, within what their prior allows, and the projected Jacobian's gradient is the
    # profiled cost's
    import torch

    from pisml_ros.ident.trajfit import _profile_level_errors, _project_levels, held_level_basis, \
        held_level_counts, held_level_variance

    torch.set_default_dtype(torch.float64)
    u = np.concatenate([np.full(50, 0.8), np.full(150, 0.81)])[:, None]
    samples = np.arange(49, 200, 5)
    counts = held_level_counts([Trajectory(0, np.arange(200.0), np.zeros((200, 1)), u)], np.array([0.01]))
    basis, precision = held_level_basis(u, np.array([0.01]), samples, counts)
    assert basis.shape == (len(samples), 1, 2)
    assert np.all(basis[samples >= 50, 0, 0] == -1) and np.all(basis[samples >= 50, 0, 1] == 1)
    np.testing.assert_allclose(precision, [np.sqrt(50) / 0.01, np.sqrt(150) / 0.01])
    assert held_level_variance(u, np.array([0.01]), counts) == pytest.approx([0.01 ** 2 / 50])
    ad = torch.tensor([[0.9, 0.05], [-0.05, 0.85]])
    bd = torch.tensor([[0.0], [0.3]])
    du_true = torch.tensor(u[samples] - 0.8)
    held_du = du_true - 0.002 * torch.tensor(basis[:, :, 0])  # the first level 2e-3 too high
    y, dx = torch.zeros(2), [torch.zeros(2)]
    for k in range(len(samples) - 1):
        y = ad @ y + bd @ du_true[k]
        dx.append(y)
    dx = torch.stack(dx)
    w = torch.tensor([1e3, 1e3])
    levels, du, responses = _profile_level_errors(ad[None], bd[None], dx[None], held_du[None], w[None],
                                                  torch.tensor(basis)[None], torch.tensor(precision)[None])
    # the deviations see the step, the two levels' difference: they share it as their priors weigh them
    # (variances 1/50 : 1/150)
    first, second = (float(v) for v in levels[0])
    assert first - second == pytest.approx(0.002, rel=0.02) and first / -second == pytest.approx(3.0, rel=0.02)
    np.testing.assert_allclose(du[0].numpy(), du_true.numpy(), atol=2e-4)
    # variable projection: J_effᵀr is the profiled cost's gradient in a coefficient moving bd
    def cost_and_jacobian(scale):
        b = bd * scale
        lv, du_eff, resp = _profile_level_errors(ad[None], b[None], dx[None], held_du[None], w[None],
                                                 torch.tensor(basis)[None], torch.tensor(precision)[None])
        y, preds, slope, slopes = torch.zeros(2), [torch.zeros(2)], torch.zeros(2), [torch.zeros(2)]
        for k in range(len(samples) - 1):
            y, slope = ad @ y + b @ du_eff[0, k], ad @ slope + bd @ du_eff[0, k]
            preds.append(y)
            slopes.append(slope)
        res = ((torch.stack(preds) - dx) * w).reshape(-1)
        jac = (torch.stack(slopes) * w).reshape(-1, 1)
        res, jac = _project_levels((res, jac), (lv, resp, torch.tensor(precision)[None]), 0, w, 1.0, 2)
        return 0.5 * float(res @ res), float(jac.T @ res)

    (up, _), (down, _), (_, gradient) = cost_and_jacobian(1.001), cost_and_jacobian(0.999), cost_and_jacobian(1.0)
    assert gradient == pytest.approx((up - down) / 0.002, rel=1e-3)


def test_both_refinement_starts_run_where_torch_has_a_second_thread():
    from pisml_ros.ident.estimators import _both_starts

    auto = IdentConfig.from_mapping({"refine_starts": "auto"})
    with torch_threads(1):
        assert not _both_starts(auto) and _both_starts(IdentConfig.from_mapping({"refine_starts": "both"}))
    with torch_threads(2):
        assert _both_starts(auto)
        # the default since stop 69: the first start alone on every thread, its long-window branch beside
        # its own prune rounds, the second start where the first's families give no consistent model
        assert not _both_starts(IdentConfig()) and IdentConfig().refine_starts == "fallback"
        assert IdentConfig().refine_long_branch


def test_a_fit_on_noisy_inputs_holds_them_and_says_so(train, small):
    from pisml_ros.ident import selection_warnings
    from pisml_ros.plant.noise import add_measurement_noise

    noisy_train = add_measurement_noise(train, 40.0, seed=6, include_inputs=True)
    noisy_small = add_measurement_noise(small, 40.0, seed=7, include_inputs=True)
    with torch_threads(2):
        est = make_estimator("pisml", IdentConfig.from_mapping({**FAST, "refine_starts": "auto"})).fit(
            noisy_train, noisy_small)
    # "auto" on two threads: the second start's family refined side by side, scored and competing
    second = est.explicit_model_.metadata["refinement_second_start"]
    assert second["run"] and second["side_by_side"] and est.metrics_["refinement_threads"] == 2.0
    assert f"refined from {second['start']}" in est.explicit_model_.metadata["selection"]["training_error_pct"]
    assert not second["early"] and "refinement_early_seconds" not in est.metrics_
    # started beside the hybrid's training instead: the same candidates, the same choice, the
    # numbers within rounding (the hybrid trains on one thread meanwhile)
    with torch_threads(2):
        early = make_estimator("pisml", IdentConfig.from_mapping(
            {**FAST, "refine_starts": "auto", "refine_second_start_early": True})).fit(noisy_train, noisy_small)
        import torch

        assert torch.get_num_threads() == 2  # (the fit gave the caller its threads back)
    assert early.explicit_model_.metadata["refinement_second_start"]["early"]
    assert early.metrics_["refinement_early_seconds"] > 0
    scores = est.explicit_model_.metadata["selection"]["training_error_pct"]
    early_scores = early.explicit_model_.metadata["selection"]["training_error_pct"]
    chosen = est.explicit_model_.metadata["selection"]["chosen"]
    assert early_scores.keys() == scores.keys() and early.explicit_model_.metadata["selection"]["chosen"] == chosen
    # (candidates far off the records, at 60-300 %, differ by up to ~3e-4 of their score here)
    assert early_scores[chosen] == pytest.approx(scores[chosen], rel=1e-4)
    np.testing.assert_allclose(early.explicit_model_.coefficients, est.explicit_model_.coefficients, rtol=1e-4,
                               atol=1e-6 * np.abs(est.explicit_model_.coefficients).max())
    held = est.explicit_model_.metadata["identification"]["inputs_denoised"]
    assert set(held) == {"training", "smallsignal"} and held["training"]["ug"]["snr_db"] == pytest.approx(40, abs=2)
    assert any("the measured inputs carry noise (ug at 40 dB SNR" in w for w in selection_warnings(est.explicit_model_))
    assert NO_SMALLSIGNAL_WARNING not in selection_warnings(est.explicit_model_)
    # off: taken as given, nothing recorded; a baseline records it too
    off = make_estimator("mod-sindy", IdentConfig.from_mapping({"input_denoise": "off"})).fit(noisy_train)
    assert off.inputs_denoised_ == {} and "inputs_denoised" not in off.explicit_model_.metadata["identification"]
    on = make_estimator("mod-sindy").fit(noisy_train)
    assert on.explicit_model_.metadata["identification"]["inputs_denoised"]["training"]["ug"]["replaced"] > 0
    with pytest.raises(ConfigError, match="input_denoise must be auto or off, got 'yes'"):
        IdentConfig.from_mapping({"input_denoise": "yes"})
    # the steps' options reach the hold (an inner interval's split only adds stretches)
    steps = make_estimator("mod-sindy", IdentConfig.from_mapping(
        {"input_interval_threshold": 6.0, "input_edge_width": 25})).fit(noisy_train)
    found = steps.explicit_model_.metadata["identification"]["inputs_denoised"]["training"]["ug"]
    assert found["stretches"] >= on.explicit_model_.metadata["identification"]["inputs_denoised"]["training"]["ug"][
        "stretches"] and found["replaced"] > 0
    with pytest.raises(ConfigError, match="input_edge_width must be >= 0"):
        IdentConfig.from_mapping({"input_edge_width": -1})


def test_a_noisy_fit_without_small_signal_records_says_what_it_lacks(train):
    from pisml_ros.ident import selection_warnings
    from pisml_ros.plant.noise import add_measurement_noise

    noisy = make_estimator("pisml", IdentConfig.from_mapping(FAST)).fit(add_measurement_noise(train, 40.0, seed=6))
    assert NO_SMALLSIGNAL_WARNING in selection_warnings(noisy.explicit_model_)
    # exact records pin the slow modes without them (the protocol's clean recordings: the same figures)
    clean = make_estimator("pisml", IdentConfig.from_mapping(FAST)).fit(train)
    assert NO_SMALLSIGNAL_WARNING not in selection_warnings(clean.explicit_model_)


def test_pure_node_has_no_explicit_model_but_a_spectrum(train, monkeypatch):
    import torch

    from pisml_ros.ident import neural
    from pisml_ros.ident.derivatives import trajectory_windows

    schedules = []
    real_optimiser = neural.optimiser

    def recording_optimiser(field, learning_rate, weight_decay, lr_schedule, steps):
        schedules.append((learning_rate, weight_decay, lr_schedule, steps))
        return real_optimiser(field, learning_rate, weight_decay, lr_schedule, steps)

    monkeypatch.setattr(neural, "optimiser", recording_optimiser)
    cfg = IdentConfig.from_mapping({"node_epochs": 2, "batch_windows": 64, "dropout": 0.05})
    est = make_estimator("node", cfg).fit(train)
    assert est.explicit_model_ is None
    # dropout is PISML's residual's (the paper's Pure NODE has none)
    assert not any(isinstance(m, torch.nn.Dropout) for m in est.model_.field.mlp.modules())
    # trained as the paper's: AdamW, OneCycle, an epoch a pass over every window in batches
    windows = len(trajectory_windows(train, cfg.window, stride=cfg.window // 2)[0])
    assert schedules == [(0.005, 1e-3, "onecycle", 2 * -(-windows // 64))]
    assert est.history_["training"]["epochs"] == [0, 1]
    assert est.model_.n_parameters > 10000
    pred = est.model_.simulate(train.select([train.trajectories[0].traj_id]))
    assert pred.trajectories[0].x.shape == train.trajectories[0].x.shape
    jac = est.model_.jacobian(train.trajectories[0].x[0], train.trajectories[0].u[0])
    assert jac.shape == (13, 13)


def test_fit_can_be_cancelled(train, small):
    calls = []

    def should_stop():
        calls.append(1)
        return len(calls) > 3

    with pytest.raises(IdentificationCancelled):
        make_estimator("pisml", IdentConfig.from_mapping(FAST)).fit(train, small, should_stop=should_stop)


def test_training_device_resolves_and_names_what_is_missing():
    import torch

    from pisml_ros.ident.neural import resolve_device

    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="'cuda'.*no CUDA GPU"):
            resolve_device("cuda")


def test_optimiser_decays_the_network_not_the_backbone_and_follows_its_schedule():
    from pisml_ros.ident.neural import build_modules, optimiser

    residual_cls, hybrid_cls = build_modules()
    field = hybrid_cls(["x", "u"], ["x", "u"], 1, xi0=np.array([[-1.0], [2.0]]), mlp=residual_cls(2, 1, (8,), 0.05))
    opt, sched = optimiser(field, 0.005, 1e-3, "onecycle", 50)
    decay = {id(p): group["weight_decay"] for group in opt.param_groups for p in group["params"]}
    assert decay.pop(id(field.xi)) == 0.0
    assert set(decay.values()) == {1e-3} and len(decay) == len(list(field.mlp.parameters()))
    rates = []
    for _ in range(50):
        rates.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert max(rates) == pytest.approx(0.005) and rates[0] < 0.001 and rates[-1] < 1e-4
    # the cosine schedule starts at the rate and ends at 5 % of it; a network alone has one group
    opt, sched = optimiser(hybrid_cls(None, ["x", "u"], 1, mlp=residual_cls(2, 1, (8,))), 1e-3, 0.0, "cosine", 10)
    assert len(opt.param_groups) == 1 and opt.param_groups[0]["lr"] == pytest.approx(1e-3)
    for _ in range(10):
        opt.step()
        sched.step()
    assert opt.param_groups[0]["lr"] == pytest.approx(5e-5)
    with pytest.raises(ValueError, match="lr_schedule must be cosine or onecycle, got 'step'"):
        optimiser(field, 1e-3, 0.0, "step", 10)
    with pytest.raises(ConfigError, match="lr_schedule must be cosine or onecycle, got 'step'"):
        IdentConfig.from_mapping({"lr_schedule": "step"})
    with pytest.raises(ConfigError, match="weight_decay must be >= 0"):
        IdentConfig.from_mapping({"weight_decay": -1e-3})


def test_unknown_method_is_named():
    with pytest.raises(ValueError, match="unknown method 'sindy'"):
        make_estimator("sindy")


def test_metrics():
    y = np.ones((10, 2))
    assert relative_error(y, y) == 0
    assert math.isclose(relative_error(1.1 * y, y), 10.0)
    assert relative_error(np.full((10, 2), np.nan), y) == math.inf
    # a small column: per column it weighs as much as the large one, taken together hardly at all
    truth = np.column_stack([np.full(10, 2.0), np.full(10, 0.01)])
    pred = truth + [0.0, 0.01]
    assert math.isclose(relative_error(pred, truth), 50.0)
    assert math.isclose(vector_relative_error(pred, truth), 100 * 0.01 / math.hypot(2.0, 0.01))
    assert vector_relative_error(np.full((10, 2), np.inf), y) == math.inf
    a = np.array([-1 + 2j, -1 - 2j, -5])
    assert spectrum_wasserstein(a, a) == 0
    assert math.isclose(spectrum_wasserstein(a, a + 3), 3.0)
    assert spectrum_wasserstein(a, a[:2]) > 0


def test_identify_simulate_analyse_cli(tmp_path, train, capsys):
    from pisml_ros.cli import main

    data = write_dataset(train, tmp_path / "train.csv")
    out = tmp_path / "model.json"
    assert main(["identify", "--data", str(data), "--method", "mod-sindy", "--out", str(out), "--quiet"]) == 0
    low, high = min(tr.u[:, 0].min() for tr in train), max(tr.u[:, 0].max() for tr in train)
    printed = capsys.readouterr().out
    assert f"identified on ug {low:.4g}-{high:.4g}\n" in printed
    assert f"training records starting at rest: {len(train)} of {len(train)}\n" in printed
    assert "estimated SNR" not in printed  # clean records
    model = ExplicitModel.load(out)
    assert model.metadata["identification"]["method"] == "mod-sindy"
    assert model.metadata["training"]["records_at_rest"] == len(train)
    assert model.metadata["training"]["sample_period"] == pytest.approx(train.dt)
    # records cut to begin 2 ms into their first transient: none at rest, and the user is told
    cut = []
    for tr in train:
        k0 = int(np.flatnonzero(np.any(np.diff(tr.u, axis=0) != 0, axis=1))[0]) + 21
        cut.append(Trajectory(tr.traj_id, tr.t[k0:] - tr.t[k0], tr.x[k0:], tr.u[k0:]))
    moving = write_dataset(Dataset(train.state_names, train.input_names, cut), tmp_path / "moving.csv")
    assert main(["identify", "--data", str(moving), "--method", "mod-sindy", "--out", str(out), "--quiet"]) == 0
    assert f"training records starting at rest: 0 of {len(train)} (constant inputs" in capsys.readouterr().out
    assert ExplicitModel.load(out).metadata["training"]["records_at_rest"] == 0
    # noisy records: the user is told the SNR the engine estimated
    from pisml_ros.plant.noise import add_measurement_noise
    noisy = write_dataset(add_measurement_noise(train, 35.0, seed=1), tmp_path / "noisy.csv")
    assert main(["identify", "--data", str(noisy), "--method", "mod-sindy", "--out", str(out), "--quiet"]) == 0
    snr = ExplicitModel.load(out).metadata["training"]["estimated_snr_db"]
    assert snr == pytest.approx(35.0, abs=0.5) and f"  records' estimated SNR {snr:.1f} dB" in capsys.readouterr().out
    pred = tmp_path / "pred.csv"
    assert main(["simulate", "--model", str(out), "--data", str(data), "--out", str(pred)]) == 0
    assert len(read_dataset(pred)) == len(train)
    printed = capsys.readouterr().out
    # the command's own computation: the records as read back, replayed through the saved model
    measured = read_dataset(data)
    cols = measured.state_index(SCORED_STATES)
    first = ExplicitModel.load(out).simulate(measured).trajectories[0].x[:, cols], measured.trajectories[0].x[:, cols]
    assert (f"trajectory {train.trajectories[0].traj_id}: relative error " in printed
            and f"ig_d, ig_q, vc_d, vc_q: {relative_error(*first):.4g} % per state, "
                f"{vector_relative_error(*first):.4g} % taken together\n" in printed), printed
    assert main(["analyse", "--model", str(out), "--ug", "0.9", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert len(report["eigenvalues"]) == 13 and "stable" in report
    # the model knows the inputs it was fitted on: an operating point outside them is flagged
    inputs = np.concatenate([tr.u for tr in train])
    coverage = report["data_coverage"]
    assert coverage["input_range"]["ug"] == [inputs[:, 0].min(), inputs[:, 0].max()]
    assert coverage["extrapolated"] is False and coverage["outside"] == []
    assert main(["analyse", "--model", str(out), "--ug", "0.9"]) == 0
    assert "extrapolated" not in capsys.readouterr().out
    narrowed = json.loads(out.read_text())
    narrowed["metadata"]["training"]["input_range"]["ug"] = [0.95, 1.2]
    out.write_text(json.dumps(narrowed))
    assert main(["analyse", "--model", str(out), "--ug", "0.9"]) == 0
    assert "note: extrapolated: outside the identification data's ug 0.95-1.2" in capsys.readouterr().out
    assert main(["analyse", "--model", str(out), "--ug", "1.0", "--margin"]) == 0
    printed = capsys.readouterr().out
    assert "stability boundaries in ug: [" in printed and "caution" not in printed
    # a model whose identification recorded cautions (selection.warnings) shows them with its analysis
    narrowed["metadata"]["selection"] = {"warnings": ["no equilibrium at grid voltage(s) 0.2: no stability verdict there"]}
    out.write_text(json.dumps(narrowed))
    assert main(["analyse", "--model", str(out), "--ug", "1.0"]) == 0
    assert "  caution: no equilibrium at grid voltage(s) 0.2: no stability verdict there\n" in capsys.readouterr().out
    # user errors: one line, status 2
    assert main(["identify", "--data", str(data), "--method", "nope", "--out", str(out)]) == 2
    assert main(["identify", "--data", str(data), "--set", "epochs=-1", "--out", str(out)]) == 2
    assert main(["identify", "--data", str(data), "--out", str(tmp_path / "m.txt")]) == 2
    assert main(["simulate", "--model", str(out), "--out", str(pred)]) == 2
    err = capsys.readouterr().err
    assert "unknown method" in err or "choose one of" in err
    assert "epochs must be > 0" in err


def _oscillator_data(n_traj, steps, seed, noise=0.01):
    """A damped oscillator driven by v (ZOH-exact samples), measured with noise at 1 % of each state's RMS."""
    import scipy.linalg

    from pisml_ros.data import Dataset, Trajectory

    a = np.array([[-15.0, 400.0], [-400.0, -15.0]])
    b = np.array([[0.0], [300.0]])
    dt = 1e-4
    disc = scipy.linalg.expm(np.block([[a, b], [np.zeros((1, 3))]]) * dt)
    rng = np.random.default_rng(seed)
    trajectories = []
    for k in range(n_traj):
        u = np.ones((401, 1))
        for at, value in steps(rng):
            u[at:] = value
        x = np.zeros((401, 2))
        x[0] = -np.linalg.solve(a, b @ u[0])
        for i in range(400):
            x[i + 1] = disc[:2, :2] @ x[i] + disc[:2, 2:] @ u[i]
        trajectories.append((np.arange(401) * dt, x, u))
    rms = np.sqrt(np.mean(np.concatenate([x for _, x, _ in trajectories]) ** 2, axis=0))
    noisy = [Trajectory(k, t, x + noise * rms * rng.standard_normal(x.shape), u)
             for k, (t, x, u) in enumerate(trajectories)]
    coefficients = np.vstack([a.T, b.T])  # terms a, b, v
    return Dataset(("xa", "xb"), ("v",), noisy, {"dt": dt}), coefficients


def test_trajectory_fit_of_noisy_records_stays_at_the_true_coefficients():
    # starting from the truth, a fit to noisy records must not wander. The small-signal responses
    # start at rest: started at their first noisy deviation sample instead, the lightly damped mode
    # rings through each record and the fit moved 11 % away (measured)
    from pisml_ros.ident.trajfit import TrajectoryFitter
    from pisml_ros.model.expressions import term_set

    train, truth = _oscillator_data(6, lambda rng: [(int(rng.integers(50, 350)), rng.uniform(0.5, 1.5))], seed=1)
    small, _ = _oscillator_data(4, lambda rng: [(50, 1.01)], seed=2)
    spread = np.concatenate([tr.x for tr in train]).std(axis=0)
    fitter = TrajectoryFitter(term_set(["xa", "xb", "v"], ("xa", "xb", "v")), 2, train.dt, window=100,
                              weights=1.0 / (0.01 * spread))
    result = fitter.fit(truth.copy(), truth != 0, train, small, lambda_jac=1.0, max_nfev=15, fit_starts_first=True)
    assert result.hessian is not None
    np.testing.assert_allclose(result.coefficients[truth != 0], truth[truth != 0], rtol=0.03)


def test_ridge_prior_collapses_a_cancelling_pair_of_nearly_collinear_terms():
    # "xa" and "xa + 1e-6*xb" are indistinguishable on the records: a start with +-500 on the pair
    # (the truth's xa coefficient plus 500 on one, -500 on the other) fits as well as the truth.
    # Without the prior the fit leaves the pair where it starts; with it the pair shares the
    # truth's coefficient and the field is unchanged
    from pisml_ros.ident.trajfit import TrajectoryFitter
    from pisml_ros.model.expressions import term_set

    train, truth = _oscillator_data(6, lambda rng: [(int(rng.integers(50, 350)), rng.uniform(0.5, 1.5))], seed=1)
    terms = ["xa", "xb", "v", "xa + 1e-6*xb"]
    start = np.vstack([truth, np.zeros((1, 2))])
    start[0] += 500.0
    start[3] -= 500.0
    spread = np.concatenate([tr.x for tr in train]).std(axis=0)

    def fit(weight):
        fitter = TrajectoryFitter(term_set(terms, ("xa", "xb", "v")), 2, train.dt, window=100,
                                  weights=1.0 / (0.01 * spread))
        return fitter.fit(start.copy(), start != 0, train, lambda_jac=0.0, max_nfev=10, fit_starts_first=True,
                          lambda_ridge=weight).coefficients

    plain, ridged = fit(0.0), fit(1e-3)
    assert np.all(np.abs(plain[3]) > 400)
    np.testing.assert_allclose(ridged[3], truth[0] / 2, rtol=0.05, atol=2.0)
    for coef in (plain, ridged):  # the pair's sum, the field the records see, stays the truth's
        np.testing.assert_allclose(coef[0] + coef[3], truth[0], rtol=0.03)
        np.testing.assert_allclose(coef[1:3], truth[1:], rtol=0.03)


def test_the_ridge_prior_holds_on_noisy_records_only():
    # its measurements were on 40 dB data; clean records pin their coefficients without it
    from pisml_ros.ident import IdentConfig
    from pisml_ros.ident.estimators import _ridge_weight

    cfg = IdentConfig(refine_ridge_weight=1e-4)
    noisy, _ = _oscillator_data(3, lambda rng: [(100, 1.2)], seed=3)
    clean, _ = _oscillator_data(3, lambda rng: [(100, 1.2)], seed=3, noise=0.0)
    assert _ridge_weight(noisy, cfg) == 1e-4
    assert _ridge_weight(clean, cfg) == 0.0


def test_verdict_uncertainty_carries_the_coefficient_covariance_to_the_largest_real_part(tmp_path, capsys):
    from pisml_ros.analysis.operating_point import operating_point_report, ug_stability_margin
    from pisml_ros.analysis.uncertainty import coefficient_covariance, covariance_metadata, max_real_std, \
        stability_verdict
    from pisml_ros.cli import main
    from pisml_ros.model import ExplicitModel

    # x' = (ug - 1)·x + y, y' = -2·y: the largest real part is ug - 1 (the x mode), 0 at ug = 1
    terms = ["x", "ug*x", "y"]
    coefficients = np.array([[-1.0, 0.0], [1.0, 0.0], [1.0, -2.0]])
    cov = np.array([[0.01, 0.002, 0.0], [0.002, 0.0004, 0.0], [0.0, 0.0, 0.09]])  # x, ug*x in x'; y in y'
    support = np.array([0, 2, 5])  # flat indices: (x, x'), (ug*x, x'), (y, y')
    meta = covariance_metadata(coefficients.shape, support, cov)
    assert meta["entries"] == [[0, 0], [1, 0], [2, 1]]
    model = ExplicitModel(("x", "y"), ("ug", "theta_g"), terms, coefficients,
                          {"coefficient_covariance": meta})
    entries, unpacked = coefficient_covariance(model)
    np.testing.assert_allclose(unpacked, cov)
    # d(ug - 1) = dc_x + ug·dc_ugx (the y' coefficient does not move the x mode)
    for ug in (0.5, 0.9, 1.3):
        expected = np.sqrt(np.array([1.0, ug]) @ cov[:2, :2] @ np.array([1.0, ug]))
        assert max_real_std(model, [0.0, 0.0], [ug, 0.0]) == pytest.approx(expected, rel=1e-9)
    assert stability_verdict(-0.5, 0.1) == "stable" and stability_verdict(0.5, 0.1) == "unstable"
    assert stability_verdict(-0.1, 0.1) == "undetermined" and stability_verdict(-0.1, None) == "stable"
    report = operating_point_report(model, 0.9)
    uncertainty = report["uncertainty"]
    std = np.sqrt(np.array([1.0, 0.9]) @ cov[:2, :2] @ np.array([1.0, 0.9]))  # 0.118: -0.1 is within 2 std
    assert uncertainty["max_real_std"] == pytest.approx(std) and uncertainty["verdict"] == "undetermined"
    np.testing.assert_allclose(uncertainty["max_real_interval"], [-0.1 - 2 * std, -0.1 + 2 * std])
    assert operating_point_report(model, 0.5)["uncertainty"]["verdict"] == "stable"
    # the ug scan names where the data leave the verdict open: |ug - 1| < 2 std (0.23 at ug 0.8,
    # 0.25 at 1.2, 0.23 at 0.7 and 0.25 at 1.3), and the boundary on a grid value counts once
    margin = ug_stability_margin(model, 0.5, ug_range=(0.5, 1.5), points=11)
    assert margin["boundaries"] == [pytest.approx(1.0, abs=1e-6)]
    assert margin["undetermined_ug"] == [[pytest.approx(0.8), pytest.approx(1.2)]]
    # without a covariance (the plant, the baselines, edited models) there is nothing to say
    bare = ExplicitModel(("x", "y"), ("ug", "theta_g"), terms, coefficients, {})
    assert "uncertainty" not in operating_point_report(bare, 0.9)
    assert "undetermined_ug" not in ug_stability_margin(bare, 0.5, ug_range=(0.5, 1.5), points=11)
    edited = ExplicitModel(("x", "y"), ("ug", "theta_g"), terms[:2], coefficients[:2],
                           {"coefficient_covariance": meta})  # entry (2, 1) no longer exists
    assert coefficient_covariance(edited) is None
    path = tmp_path / "model.json"
    model.save(path)
    assert main(["analyse", "--model", str(path), "--ug", "0.9", "--margin"]) == 0
    printed = capsys.readouterr().out
    assert "stability undetermined by the data" in printed
    assert "stability not decided by the data (largest real part within 2 std of 0) at ug 0.8-1.2" in printed


def test_training_error_runs_records_from_their_rest_means():
    from pisml_ros.analysis.metrics import relative_error
    from pisml_ros.data.dataset import steady_start_length
    from pisml_ros.ident.estimators import _rest_started, training_error
    from pisml_ros.model import ExplicitModel

    train, truth = _oscillator_data(4, lambda rng: [(int(rng.integers(50, 350)), rng.uniform(0.5, 1.5))], seed=1)
    model = ExplicitModel(("xa", "xb"), ("v",), ["xa", "xb", "v"], truth)
    started = _rest_started(train)
    for tr, rest in zip(train, started):
        end = steady_start_length(tr)  # the first input step
        assert 50 <= end < 350
        np.testing.assert_array_equal(rest.x[1:], tr.x[1:])
        np.testing.assert_allclose(rest.x[0], tr.x[:end].mean(axis=0), rtol=1e-12)
    from_first = np.mean([relative_error(p.x, t.x) for p, t in zip(model.simulate(train), train)])
    # the true model: from the rest means only the records' own noise is left
    assert training_error(model, train) < 0.9 * from_first
    clean, _ = _oscillator_data(2, lambda rng: [(100, 1.2)], seed=3, noise=0.0)
    for tr, rest in zip(clean, _rest_started(clean)):
        np.testing.assert_allclose(rest.x, tr.x, rtol=0, atol=1e-12)


def test_training_errors_of_a_family_run_together_and_match_one_by_one():
    from pisml_ros.ident.estimators import training_error, training_errors
    from pisml_ros.model import ExplicitModel

    train, truth = _oscillator_data(4, lambda rng: [(int(rng.integers(50, 350)), rng.uniform(0.5, 1.5))], seed=1)
    terms = ["xa", "xb", "v"]
    models = {"truth": ExplicitModel(("xa", "xb"), ("v",), terms, truth),
              "off": ExplicitModel(("xa", "xb"), ("v",), terms, truth * 1.1),
              # grows at ~+1e4 1/s: diverges in the 40 ms records, without spoiling the others
              "unstable": ExplicitModel(("xa", "xb"), ("v",), terms, truth + np.array([[1e4, 0.0], [0.0, 0.0], [0.0, 0.0]])),
              "other terms": ExplicitModel(("xa", "xb"), ("v",), ["xa", "xb", "v", "xa*xb"], np.vstack([truth, [[0.0, 1.0]]]))}
    together = training_errors(models, train)
    assert together == {name: training_error(model, train) for name, model in models.items()}
    assert together["unstable"] == float("inf") and np.isfinite(together["truth"])
    assert together["truth"] < together["off"]


def test_a_growing_stage_keeps_at_most_its_windows():
    """``refine_growing_max_windows``: a stage fits that many windows, evenly spread; 0 all of them."""
    from pisml_ros.ident import IdentConfig
    from pisml_ros.ident.estimators import refine_explicit
    from pisml_ros.model import ExplicitModel

    train, truth = _oscillator_data(4, lambda rng: [(int(rng.integers(50, 350)), rng.uniform(0.5, 1.5))], seed=1)
    model = ExplicitModel(("xa", "xb"), ("v",), ["xa", "xb", "v"], truth * 1.1)
    settings = {"refine_growing_windows": "10,25", "refine_growing_evaluations": "2,2", "refine_prune_budgets": ""}
    every = [sum((len(tr) - 1) // w for tr in train) for w in (10, 25)]
    for most, windows in (("", every), ("7,0", [7, every[1]]), ("0,1000", every)):
        cfg = IdentConfig.from_mapping({**settings, "refine_growing_max_windows": most})
        out = refine_explicit(model, train, None, cfg)
        assert [stage["windows"] for stage in out["refined"].metadata["refinement"]["stages"]] == windows


@pytest.mark.slow
def test_noisy_data_refinement_grows_its_windows_and_prunes_a_spurious_term():
    # from 20-30 % off, with a spurious product term, on noisy records: the stages of growing windows
    # bring the true coefficients back, and the pruned, re-fitted model drops the spurious term
    from pisml_ros.ident import IdentConfig
    from pisml_ros.ident.estimators import refine_explicit
    from pisml_ros.model import ExplicitModel

    train, truth = _oscillator_data(6, lambda rng: [(int(rng.integers(50, 350)), rng.uniform(0.5, 1.5))], seed=1)
    small, _ = _oscillator_data(4, lambda rng: [(50, 1.01)], seed=2)
    start = np.vstack([truth * (1 + 0.25 * np.array([[1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]])), [[30.0, -30.0]]])
    model = ExplicitModel(("xa", "xb"), ("v",), ["xa", "xb", "v", "xa*xb"], start)
    cfg = IdentConfig.from_mapping({"refine_growing_windows": "10,50", "refine_growing_evaluations": "10,8",
                                    "refine_polish_windows": "100", "refine_polish_evaluations": "6",
                                    "refine_prune_budgets": "0.01", "refine_long_branch": False})
    progress = []
    out = refine_explicit(model, train, small, cfg, progress=lambda fraction, losses: progress.append(fraction))
    assert set(out) == {"refined", "pruned +1 %"}
    assert out["refined"].metadata["refinement"]["growing_windows"]["windows"] == [10, 50]
    np.testing.assert_allclose(out["refined"].coefficients[:3], truth, rtol=0.05, atol=0.02 * np.abs(truth).max())
    pruned = out["pruned +1 %"]
    assert np.all(pruned.coefficients[3] == 0) and np.all(pruned.coefficients[:3][truth != 0] != 0)
    np.testing.assert_allclose(pruned.coefficients[:3], truth, rtol=0.05, atol=0.02 * np.abs(truth).max())
    assert progress and progress[-1] == pytest.approx(1.0) and all(np.diff(progress) >= 0)
    # where the time went: a record per stage (bench/fit_time.py reads them)
    stages = out["refined"].metadata["refinement"]["stages"]
    assert [stage["window"] for stage in stages] == [10, 50] and stages[0]["support"] == np.count_nonzero(start)
    assert [stage["windows"] for stage in stages] == [sum((len(tr) - 1) // w for tr in train) for w in (10, 50)]
    for stage, budget in zip(stages, (10, 8)):
        assert 0 <= stage["accepted"] < stage["evaluations"] <= budget and stage["seconds"] > 0
    assert stages[-1]["cost"] == out["refined"].metadata["refinement"]["cost"]
    polish = pruned.metadata["pruning"]["polish_stages"]
    assert [stage["window"] for stage in polish] == [100]
    assert polish[0]["support"] == np.count_nonzero(pruned.coefficients)
    # each candidate carries its coefficients' covariance for the noise (the analysis' verdict
    # uncertainty): over its own support, and the truth within a few of its standard deviations
    from pisml_ros.analysis.uncertainty import coefficient_covariance

    for candidate in out.values():
        entries, cov = coefficient_covariance(candidate)
        assert sorted(map(tuple, entries.tolist())) == sorted(zip(*np.nonzero(candidate.coefficients)))
        true = np.vstack([truth, [[0.0, 0.0]]])[entries[:, 0], entries[:, 1]]
        z = (candidate.coefficients[entries[:, 0], entries[:, 1]] - true) / np.sqrt(np.diag(cov))
        assert np.all(np.abs(z) < 4), z
    # prune-and-polish rounds: the first drops both spurious terms; a second would drop nothing more,
    # so it adds no candidate (another polish of the same support)
    spurious = ExplicitModel(("xa", "xb"), ("v",), ["xa", "xb", "v", "xa*xb", "xb*v"],
                             np.vstack([start, [[-20.0, 20.0]]]))
    rounds = refine_explicit(spurious, train, small, IdentConfig.from_mapping({**cfg.to_dict(), "refine_prune_rounds": 3}))
    assert set(rounds) == {"refined", "pruned +1 %"}
    assert rounds["pruned +1 %"].metadata["pruning"]["round"] == 1
    # the budget is the nominal fraction for the reference number of samples, scaled to these records
    samples = train.n_samples
    pruning = rounds["pruned +1 %"].metadata["pruning"]
    assert pruning["training_samples"] == samples and pruning["nominal_budget"] == 0.01
    assert pruning["budget"] == pytest.approx(0.01 * 4812 / samples)
    assert np.all(rounds["pruned +1 %"].coefficients[3:] == 0)
    np.testing.assert_allclose(rounds["pruned +1 %"].coefficients[:3], truth, rtol=0.05, atol=0.02 * np.abs(truth).max())
    # the long-window branch: the refined model re-fitted in the polish's longest windows, then pruned
    # and polished there, a family of its own beside the first (which it leaves as it was)
    from pisml_ros.ident.selection import LONG_BRANCH_SUFFIX, _refinement_family

    branched = refine_explicit(spurious, train, small, IdentConfig.from_mapping(
        {**cfg.to_dict(), "refine_prune_rounds": 3, "refine_long_branch": True, "refine_long_branch_evaluations": 3}))
    assert set(branched) == {"refined", "pruned +1 %", "refined at long windows", "pruned +1 % at long windows"}
    assert {_refinement_family(name) for name in branched} == {"", LONG_BRANCH_SUFFIX}
    for name in ("refined", "pruned +1 %"):
        np.testing.assert_array_equal(branched[name].coefficients, rounds[name].coefficients)
    long_stages = branched["refined at long windows"].metadata["refinement"]["stages"]
    assert [stage["window"] for stage in long_stages] == [100] and long_stages[0]["evaluations"] <= 3
    long_pruned = branched["pruned +1 % at long windows"]
    assert long_pruned.metadata["pruning"]["polish_windows"] == [100]
    assert np.all(long_pruned.coefficients[3:] == 0)
    np.testing.assert_allclose(long_pruned.coefficients[:3], truth, rtol=0.05, atol=0.02 * np.abs(truth).max())
    # ranked by degree (the products go first) the rounds come to the same support here
    ranked = refine_explicit(spurious, train, small, IdentConfig.from_mapping(
        {**cfg.to_dict(), "refine_prune_rounds": 3, "refine_prune_degree_preference": 10}))
    assert set(ranked) == {"refined", "pruned +1 %"}
    assert (ranked["pruned +1 %"].coefficients != 0).tolist() == (rounds["pruned +1 %"].coefficients != 0).tolist()
    # empty growing windows: the one-stage refinement (with its pruned candidates), as on clean data
    one_stage = refine_explicit(model, train, small, IdentConfig.from_mapping(
        {"refine_growing_windows": "", "refine_prune_budgets": "0.01", "refine_window": 50, "refine_max_nfev": 3}))
    assert "growing_windows" not in one_stage["refined"].metadata["refinement"]


def test_refinement_keeps_its_rk4_step_below_refine_max_step(monkeypatch):
    # coarse samples get more RK4 substeps (RK4's own error would bias the coefficients); fine ones
    # keep the configured two
    from pisml_ros.ident.estimators import refine_explicit
    from pisml_ros.model import ExplicitModel

    from pisml_ros.ident import trajfit

    train, truth = _oscillator_data(4, lambda rng: [(int(rng.integers(50, 350)), rng.uniform(0.5, 1.5))], seed=3)
    model = ExplicitModel(("xa", "xb"), ("v",), ["xa", "xb", "v"], truth * 1.05)
    one_stage = {"refine_growing_windows": "", "refine_prune_budgets": "", "refine_window": 50, "refine_max_nfev": 3}
    built = []  # the substeps the fitters were built with

    class Recording(trajfit.TrajectoryFitter):
        def __init__(self, *args, **kwargs):
            built.append(kwargs["substeps"])
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(trajfit, "TrajectoryFitter", Recording)
    substeps = {}
    for max_step in (0.0, 5e-5, 2.5e-5, 1.2e-5):
        built.clear()
        out = refine_explicit(model, train, None, IdentConfig.from_mapping({**one_stage, "refine_max_step": max_step}))
        substeps[max_step] = out["refined"].metadata["refinement"]["rk4_substeps"]
        assert set(built) == set(substeps[max_step])
        np.testing.assert_allclose(out["refined"].coefficients, truth, rtol=0.05, atol=0.02 * np.abs(truth).max())
    assert substeps == {0.0: [2], 5e-5: [2], 2.5e-5: [4], 1.2e-5: [9]}  # dt 1e-4


def test_refinement_shares_its_windows_out_in_at_most_two_parts(monkeypatch):
    # on a many-core machine torch has a thread per core, but parts past two contend for the GIL (a
    # 16-core machine: 0.85 / 0.76 / 2.9 / 6.1 s per evaluation in 1 / 2 / 8 / 16 parts)
    import threading

    from pisml_ros.ident import IdentConfig
    from pisml_ros.ident.estimators import refine_explicit
    from pisml_ros.ident.trajfit import SHOOTING_PARTS_MAX
    from pisml_ros.model import ExplicitModel

    train, truth = _oscillator_data(4, lambda rng: [(int(rng.integers(50, 350)), rng.uniform(0.5, 1.5))], seed=1)
    model = ExplicitModel(("xa", "xb"), ("v",), ["xa", "xb", "v"], truth * 1.1)
    cfg = IdentConfig.from_mapping({"refine_growing_windows": "10", "refine_growing_evaluations": "3",
                                    "refine_polish_windows": "", "refine_polish_evaluations": "",
                                    "refine_prune_budgets": ""})
    seen = []

    def progress(fraction, losses):
        seen.append(sum(t.name.startswith("pisml-shoot") for t in threading.enumerate()))

    with torch_threads(6):
        refine_explicit(model, train, None, cfg, progress=progress)
    assert seen and 0 < max(seen) <= SHOOTING_PARTS_MAX == 2, seen


def test_integral_form_spline_quadrature_and_input_jumps():
    from pisml_ros.data import Dataset, Trajectory
    from pisml_ros.ident.derivatives import input_jumps, integral_form
    from pisml_ros.model.expressions import term_set

    # a 1.5 kHz rotation sampled at 10 kHz (~6.7 samples per period, like the LCL modes)
    w, dt, n = 2 * np.pi * 1500.0, 1e-4, 400
    t = np.arange(n) * dt
    v = np.where(np.arange(n) < 200, 1.0, 0.8)  # an input jump between samples 199 and 200
    data = Dataset(("x1", "x2"), ("v",), [Trajectory(0, t, np.column_stack([np.sin(w * t), np.cos(w * t)]), v[:, None])])
    truth = np.array([[0.0, -w], [w, 0.0]])  # x1' = w x2, x2' = -w x1 over terms x1, x2
    ts = term_set(["x1", "x2"], ("x1", "x2", "v"))

    def misfit(a, b):
        return np.linalg.norm(a @ truth - b) / np.linalg.norm(b)

    a, b = integral_form(data, ts, span=10)
    assert a.shape[0] == n - 10 and misfit(a, b) > 0.03  # the trapezoid rule: ~(w dt)^2 / 12
    a, b = integral_form(data, ts, span=10, quadrature="spline")
    assert a.shape[0] == n - 10 - 10  # the ten windows across the jump are dropped
    assert misfit(a, b) < 0.01
    with pytest.raises(ValueError, match="quadrature"):
        integral_form(data, ts, quadrature="simpson")
    # jumps of piecewise-constant inputs, and a step in a noisy input (not its noise)
    assert np.flatnonzero(input_jumps(v[:, None])).tolist() == [199]
    noisy = v[:, None] + 1e-3 * np.random.default_rng(0).standard_normal((n, 1))
    assert np.flatnonzero(input_jumps(noisy)).tolist() == [199]


def test_sparse_refit_recovers_the_structure_of_clean_records():
    from pisml_ros.ident.refit import sparse_refit

    train, truth = _oscillator_data(6, lambda rng: [(int(rng.integers(50, 350)), rng.uniform(0.5, 1.5))], seed=1,
                                    noise=0.0)
    # the true terms plus spurious ones, some nearly collinear with them over these records
    terms = ["xa", "xb", "v", "1", "xa**2", "xa*xb", "xb*v", "xa*v"]
    dense, sparse = sparse_refit(train, terms, budgets=[0.0, 3.0])
    assert np.count_nonzero(dense) == len(terms) * 2
    assert np.array_equal(sparse[:3] != 0, truth != 0) and not np.any(sparse[3:])
    np.testing.assert_allclose(sparse[:3][truth != 0], truth[truth != 0], rtol=1e-3)
    with pytest.raises(ValueError, match="too short"):
        sparse_refit(train, terms, budgets=[1.0], span=399)


def test_least_squares_elimination_ranks_removals_where_the_normal_equations_cannot():
    # a nearly collinear pair (cond ~3e6: ~1e13 for aᵀa) and an equation error ~1e-20 of b's
    # energy, as on clean records of an inverter whose grid and filter currents nearly coincide
    from pisml_ros.ident.refit import least_squares_elimination

    t = np.linspace(0, 1, 2000)
    c = np.cos(2 * np.pi * t)
    a = np.column_stack([np.sin(2 * np.pi * t), c, c + 1e-6 * np.sin(6 * np.pi * t), t, t ** 2, np.ones_like(t)])
    b = 3.0 * a[:, 0] - 0.5 * a[:, 3] + 1e-11 * np.random.default_rng(0).standard_normal(t.size)
    least = 0.5 * np.sum((a @ np.linalg.lstsq(a, b, rcond=None)[0] - b) ** 2)
    some = least_squares_elimination(a, b, [10 * least])[0]
    assert np.flatnonzero(some).tolist() == [0, 3]
    np.testing.assert_allclose(some[[0, 3]], [3.0, -0.5], rtol=1e-9)
    # a column that carries nothing goes first, at no cost
    zero = least_squares_elimination(np.column_stack([a[:, [0, 3]], np.zeros_like(t)]), b, [0.0])[0]
    assert np.flatnonzero(zero).tolist() == [0, 1]


def test_selection_excuses_a_fold_just_before_an_edge_rest_point_that_the_model_passes_slowly():
    from pisml_ros.analysis.operating_point import rest_drift
    from pisml_ros.ident.selection import _selected

    # x' = 1 - x; y' = a - u - y**2 has a stable equilibrium y = sqrt(a - u) for u < a and none
    # beyond: at u = 1 (a record at rest at y = 0.01, at the edge of the data) a = 0.9999 passes
    # by at 2e-4 1/s, a = 0.7 leaves at 0.3 1/s
    terms = ["1", "x", "u", "y**2", "y"]

    def model(column_y):
        return ExplicitModel(("x", "y"), ("u",), terms, np.column_stack([[1.0, -1, 0, 0, 0], column_y]), {})

    points = [{"inputs": [0.0], "state": [1.0, 1.0]}, {"inputs": [0.5], "state": [1.0, 0.707]},
              {"inputs": [1.0], "state": [1.0, 0.01]}]
    fold, fast = model([0.9999, 0, -1, -1, 0]), model([0.7, 0, -1, -1, 0])
    assert rest_drift(fold, points[2], 1.0, 0.1) < 1e-3
    assert rest_drift(fast, points[2], 1.0, 0.1) >= 0.1
    assert rest_drift(fast, points[2], 1.0, 0.1, max_evaluations=3) == np.inf
    template = ExplicitModel(("x", "y"), ("u",), terms, np.zeros((5, 2)), {"reference_points": points})
    candidates = {"backbone": model([1.0, 0, -1, 0, -1]),  # y' = 1 - u - y: an equilibrium at every point
                  "distilled": fold, "re-fit +100 %": fast,
                  "re-fit +300 %": model([1e-4, 0, 0, 0, 0])}  # no equilibrium anywhere, however slow
    scores = {"backbone": 0.05, "distilled": 0.01, "re-fit +100 %": 0.005, "re-fit +300 %": 0.001}
    selection = _selected(template, candidates, scores, unstable_rate=1.0).metadata["selection"]
    assert selection["chosen"] == "distilled"
    assert selection["inconsistent_rest_points"] == {"backbone": 0, "distilled": 0, "re-fit +100 %": 1,
                                                     "re-fit +300 %": 3}
    # where the small-signal records sat at rest there is no excuse: they are perturbations about an
    # equilibrium they return to, and the analysis is asked for there
    flagged = ExplicitModel(("x", "y"), ("u",), terms, np.zeros((5, 2)),
                            {"reference_points": points[:2] + [dict(points[2], smallsignal=True)]})
    at_small = _selected(flagged, candidates, scores, unstable_rate=1.0).metadata["selection"]
    assert at_small["inconsistent_rest_points"]["distilled"] == 1 and at_small["chosen"] == "backbone"
    # a hole between two points with an equilibrium is no fold at the branch's edge: never excused.
    # y' = 4 (u - 0.5)**2 - 1e-4 - y**2 has an equilibrium at u = 0 and u = 1, none at u = 0.5,
    # where it passes y = 0.01 as slowly as the fold above
    from pisml_ros.ident.selection import _inconsistent_points
    hole = ExplicitModel(("x", "y"), ("u",), terms + ["u**2"],
                         np.column_stack([[1.0, -1, 0, 0, 0, 0], [0.9999, 0, -4, -1, 0, 4]]), {})
    around = [{"inputs": [0.0], "state": [1.0, 1.0]}, {"inputs": [0.5], "state": [1.0, 0.01]},
              {"inputs": [1.0], "state": [1.0, 1.0]}]
    assert rest_drift(hole, around[1], 1.0, 0.1) < 1e-3
    assert _inconsistent_points("hole", {"hole": hole}, around, {}, 1.0) == 1
    assert _inconsistent_points("fold", {"fold": fold}, points, {}, 1.0) == 0
    # without a finite growth rate (the default: growth unchecked) there is no time scale to drift on,
    # and a missing equilibrium counts as it always did
    assert _selected(template, candidates, scores).metadata["selection"]["chosen"] == "backbone"
    # a candidate worse than holding the records' first states is no model, consistent or not: the
    # consistent backbone at 0.05 loses to the inconsistent re-fits when holding scores 0.04
    held = _selected(template, candidates, scores, unstable_rate=1.0, hold=0.04).metadata["selection"]
    assert held["chosen"] == "distilled" and held["hold_error_pct"] == 0.04
    assert _selected(template, candidates, scores, hold=0.04).metadata["selection"]["chosen"] == "re-fit +100 %"
    # where none beats holding, all compete on their scores alone: the consistent backbone does not
    # win over better-scoring inconsistent ones (20 dB: a pruning collapsed to one term per
    # equation, consistent at every rest point, scored 289 % against the best's 53 %, hold 45 %)
    none = _selected(template, candidates, scores, unstable_rate=1.0, hold=1e-4).metadata["selection"]
    assert none["chosen"] == "re-fit +300 %" and none["inconsistent_rest_points"]["re-fit +300 %"] == 3


def test_a_mode_that_does_not_decay_where_the_small_signal_records_sat_is_inconsistent():
    from pisml_ros.ident.selection import _inconsistent_points

    # x' = 1 - x; y' = r (y - 1): the equilibrium (1, 1) has the modes -1 and r at every input;
    # y' = -(y - 1)**3 has an isolated equilibrium there with the mode 0
    terms = ["1", "x", "y", "y**2", "y**3"]

    def model(column_y):
        return ExplicitModel(("x", "y"), ("u",), terms, np.column_stack([[1.0, -1, 0, 0, 0], column_y]), {})

    candidates = {name: model([-rate, 0, rate, 0, 0])
                  for name, rate in (("slow growth", 0.3), ("decay", -0.5), ("fast growth", 3.0),
                                     ("zero mode", -1e-3))}
    candidates["no decay"] = model([1.0, 0, -3, 3, -1])
    training = [{"inputs": [0.8], "state": [1.0, 1.0]}, {"inputs": [1.2], "state": [1.0, 1.0]}]
    small = training + [{"inputs": [1.0], "state": [1.0, 1.0], "smallsignal": True}]
    count = {name: (_inconsistent_points(name, candidates, training, {}, 1.0),
                    _inconsistent_points(name, candidates, small, {}, 1.0)) for name in candidates}
    # where a training record sat, growth slower than the tolerated rate passes (the plant itself
    # grows at +0.25 1/s at ug 1.2); where the small-signal records sat, perturbations that return
    # to their equilibrium, it does not (stop 39: a 40 dB fit unstable at +0.15-0.25 1/s at every
    # rest point, spuriously unstable over ug 0.2-1.1)
    # a mode of modulus below selection.ZERO_MODE_MODULUS (a decay at 1e-3 1/s, or none: the cubic)
    # counts as no equilibrium at every point: the smallest offset in f moves such an equilibrium
    # far (stop 61: Q 2.6e3 p.u. off the plant's), and at none of them is it excused as a fold
    assert count == {"slow growth": (0, 1), "decay": (0, 0), "fast growth": (2, 3), "zero mode": (2, 3),
                     "no decay": (2, 3)}
    # an infinite rate leaves growth unchecked, there too; a missing equilibrium still counts
    assert [_inconsistent_points(name, candidates, small, {}, np.inf) for name in candidates] == [0, 0, 0, 3, 3]
    from pisml_ros.analysis.operating_point import growth_rates_at_points

    assert growth_rates_at_points(candidates["zero mode"], training) == pytest.approx([-1e-3, -1e-3])
    assert growth_rates_at_points(candidates["zero mode"], training, zero_mode_below=0.01) == [None, None]


def test_an_equilibrium_away_from_the_rest_state_is_inconsistent_with_a_rest_offset():
    """``selection_rest_offset``: where a record sat still, the model's equilibrium must lie within
    that (relative) of the rest state; inf: off."""
    from pisml_ros.ident import IdentConfig
    from pisml_ros.ident.selection import _inconsistent_points, _rest_offsets

    # x' = a - x, y' = u - y: the equilibrium (a, u), stable, with the rest states at (1, u)
    def model(a):
        return ExplicitModel(("x", "y"), ("u",), ["1", "x", "y", "u"],
                             np.array([[a, 0.0], [-1.0, 0.0], [0.0, -1.0], [0.0, 1.0]]), {})

    candidates = {"at rest": model(1.02), "away": model(1.5)}
    points = [{"inputs": [u], "state": [1.0, u]} for u in (0.8, 1.2)]
    cache: dict = {}
    for u, offset in zip((0.8, 1.2), _rest_offsets("away", candidates, points, cache)):
        assert offset == pytest.approx(0.5 / np.hypot(1.0, u))
    assert [_inconsistent_points(name, candidates, points, cache, 1.0) for name in candidates] == [0, 0]
    assert [_inconsistent_points(name, candidates, points, cache, 1.0, rest_offset=0.1)
            for name in candidates] == [0, 2]
    assert IdentConfig().selection_rest_offset == 0.3  # (0.1 at stop 69, 0.3 since stop 70)
    with pytest.raises(ConfigError, match="selection_rest_offset"):
        IdentConfig.from_mapping({"selection_rest_offset": -1})


def test_selection_prefers_a_candidate_with_equilibria_over_the_analysis_grid():
    from pisml_ros.ident.selection import _grid_inputs, _selected

    # y' = ug - a - y**2 has the stable equilibrium y = sqrt(ug - a) for ug > a and none below: with
    # a = 0.7 the branch folds at ug 0.7, below the records' rest points (ug 0.8 and 1.0), as
    # recording 4's chosen model did at 40 dB; with a = 0 it reaches every grid voltage
    terms = ["1", "x", "ug", "y**2"]

    def model(a, b=0.0):  # b (1 - x) in y' adds two coefficients that vanish at rest (x = 1)
        return ExplicitModel(("x", "y"), ("ug", "theta_g"), terms,
                             np.array([[1.0, b - a], [-1, -b], [0, 1], [0, -1]]), {})

    points = [{"inputs": [0.8, 0.3], "state": [1.0, 0.3]}, {"inputs": [1.0, 0.1], "state": [1.0, 0.55]}]
    template = ExplicitModel(("x", "y"), ("ug", "theta_g"), terms, np.zeros((4, 2)), {"reference_points": points})
    grid = (0.2, 0.4, 0.6, 0.8, 1.0)
    # the grid voltages at grid phase 0, other inputs (none here) as at the lowest rest point
    assert [list(v) for v in _grid_inputs(template, grid)] == [[g, 0.0] for g in grid]
    assert _grid_inputs(template, ()) == []
    candidates = {"pruned +0.1 % x3": model(0.7), "pruned +0.1 %": model(0.0, 0.01), "refined": model(0.0, 0.01)}
    scores = {"pruned +0.1 % x3": 0.02, "pruned +0.1 %": 0.03, "refined": float("inf")}
    # both prunings are consistent with the rest points: without the grid the better score wins,
    # the sparser model by the tolerance
    assert _selected(template, candidates, scores, tolerance=0.5, unstable_rate=1.0).metadata["selection"][
        "chosen"] == "pruned +0.1 % x3"
    selection = _selected(template, candidates, scores, tolerance=0.5, unstable_rate=1.0,
                          equilibrium_grid=grid).metadata["selection"]
    assert selection["chosen"] == "pruned +0.1 %"
    assert selection["missing_equilibria"] == {"pruned +0.1 % x3": 3, "pruned +0.1 %": 0}
    # the grid only breaks ties among the candidates consistent with the rest points: one with a
    # whole branch but unstable at the rest points (y' = y**2 - ug: the branch y = -sqrt(ug) is
    # stable, the rest states sit near the unstable one) does not win
    candidates["pruned +0.1 %"] = ExplicitModel(("x", "y"), ("ug", "theta_g"), terms,
                                                np.array([[1.0, 0], [-1, 0], [0, -1], [0, 1]]), {})
    selection = _selected(template, candidates, scores, tolerance=0.5, unstable_rate=1.0,
                          equilibrium_grid=grid).metadata["selection"]
    assert selection["chosen"] == "pruned +0.1 % x3" and selection["inconsistent_rest_points"]["pruned +0.1 %"] == 2
    # nor where no candidate reproduces the records better than holding their first states: the best
    # score stands (a collapsed pruning with a whole branch took 20 dB data to 123 % IOD, stop 41)
    candidates["pruned +0.1 %"] = model(0.0, 0.01)
    assert _selected(template, candidates, scores, tolerance=0.5, unstable_rate=1.0, equilibrium_grid=grid,
                     hold=0.01).metadata["selection"]["chosen"] == "pruned +0.1 % x3"
    assert _selected(template, candidates, scores, tolerance=0.5, unstable_rate=1.0, equilibrium_grid=grid,
                     hold=0.05).metadata["selection"]["chosen"] == "pruned +0.1 %"
    # nor does a candidate far worse than the noise explains (above ratio x floor + margin) displace a
    # choice within that: stop 54, a current limit's family at 4.0 % against a threshold of 4.1 %
    # lost to a model at 10 % for its equilibria
    scores["pruned +0.1 %"] = 0.3
    assert _selected(template, candidates, scores, tolerance=0.5, unstable_rate=1.0, equilibrium_grid=grid,
                     noise_floor=0.05, noise_ratio=2.5, noise_margin=0.0).metadata["selection"]["chosen"] == \
        "pruned +0.1 % x3"
    assert _selected(template, candidates, scores, tolerance=0.5, unstable_rate=1.0, equilibrium_grid=grid,
                     noise_floor=0.2, noise_ratio=2.5, noise_margin=0.0).metadata["selection"]["chosen"] == \
        "pruned +0.1 %"


def test_the_grid_stability_option_passes_over_a_sparser_model_unstable_where_the_best_is_stable():
    from pisml_ros.ident.selection import _selected

    # x' = 1 - x; y' = k·y + (ug-dependent part): the equilibrium y = 0 at every grid voltage.
    # "flips": y' = (0.5 - ug)·y, stable at the rest points (ug 0.8, 1.0) but unstable below ug 0.5
    # (stop 43: a 40 dB fit's sparser model unstable at ug 0.2 and 0.4, the plant stable there);
    # "stable": y' = -y + 0.1·(x - 1), stable everywhere, one coefficient more
    terms = ["1", "x", "y", "ug*y"]

    def model(y_column):
        return ExplicitModel(("x", "y"), ("ug", "theta_g"), terms, np.column_stack([[1.0, -1, 0, 0], y_column]), {})

    flips, stable = model([0, 0, 0.5, -1]), model([-0.1, 0.1, -1, 0])
    points = [{"inputs": [0.8, 0.0], "state": [1.0, 0.0]}, {"inputs": [1.0, 0.0], "state": [1.0, 0.0]}]
    template = ExplicitModel(("x", "y"), ("ug", "theta_g"), terms, np.zeros((4, 2)), {"reference_points": points})
    grid = (0.2, 0.4, 0.6, 0.8, 1.0)
    candidates = {"pruned +0.1 %": stable, "pruned +0.1 % x2": flips, "refined": stable}
    scores = {"pruned +0.1 %": 0.020, "pruned +0.1 % x2": 0.021, "refined": float("inf")}

    def chosen(**options):
        return _selected(template, candidates, scores, tolerance=0.5, unstable_rate=1.0, equilibrium_grid=grid,
                         **options).metadata["selection"]

    # without the check the sparser model wins by the tolerance (it has every equilibrium)
    assert chosen()["chosen"] == "pruned +0.1 % x2" and chosen()["turned_unstable"] == {}
    selection = chosen(grid_stability=True)
    assert selection["chosen"] == "pruned +0.1 %" and selection["grid_stability"] is True
    assert selection["turned_unstable"] == {"pruned +0.1 % x2": [0.2, 0.4]}
    # only that direction: a sparser model stable where the best is unstable is taken
    candidates.update({"pruned +0.1 %": model([-0.1, 0.1, 0.5, -1]), "pruned +0.1 % x2": model([0, 0, -1, 0])})
    selection = chosen(grid_stability=True)
    assert selection["chosen"] == "pruned +0.1 % x2" and selection["turned_unstable"] == {}


def test_selection_records_in_words_what_is_wrong_with_the_chosen_model():
    from pisml_ros.ident import selection_warnings
    from pisml_ros.ident.selection import _selected

    terms = ["1", "x", "ug", "y**2"]

    def model(a, b=0.0):  # as above: y' = ug - a - y**2 folds at ug = a
        return ExplicitModel(("x", "y"), ("ug", "theta_g"), terms,
                             np.array([[1.0, b - a], [-1, -b], [0, 1], [0, -1]]), {})

    points = [{"inputs": [0.8, 0.3], "state": [1.0, 0.3]}, {"inputs": [1.0, 0.1], "state": [1.0, 0.55]}]
    template = ExplicitModel(("x", "y"), ("ug", "theta_g"), terms, np.zeros((4, 2)), {"reference_points": points})
    grid = (0.2, 0.4, 0.6, 0.8, 1.0)
    # a sound model: nothing to say
    sound = _selected(template, {"refined": model(0.0)}, {"refined": 0.02}, unstable_rate=1.0, hold=0.4,
                      equilibrium_grid=grid)
    assert selection_warnings(sound) == []
    # the only candidate folds at ug 0.7 (no verdict at 0.2-0.6) and scores worse than the hold
    poor = _selected(template, {"refined": model(0.7)}, {"refined": 0.5}, unstable_rate=1.0, hold=0.4,
                     equilibrium_grid=grid)
    warnings = selection_warnings(poor)
    assert len(warnings) == 2
    assert "no better than holding" in warnings[0] and "0.5 % against 0.4 %" in warnings[0]
    assert warnings[1].startswith("no equilibrium at grid voltage(s) 0.2, 0.4, 0.6:")
    # unstable where the records sat at rest (y' = y**2 - ug: the rest states sit near the unstable branch)
    unstable = ExplicitModel(("x", "y"), ("ug", "theta_g"), terms, np.array([[1.0, 0], [-1, 0], [0, -1], [0, 1]]), {})
    warnings = selection_warnings(_selected(template, {"refined": unstable}, {"refined": 0.02}, unstable_rate=1.0,
                                            hold=0.4))
    assert warnings == [warnings[0]] and warnings[0].startswith("at 2 of the 2 operating points where the records sat")
    # far worse than the noise explains, with the default ratio and margin (IdentConfig: 2.5x the
    # floor plus 0.1 points): 5 kHz seed 1 at 40 dB, 7.2 % against 1.84 %, and protocol seed 19,
    # 4.86 % against 1.85 %; the worst sound 40 dB fit scored 2.37x its floor (4.34 % against 1.83 %)
    defaults = IdentConfig()

    def far(error, floor):
        return selection_warnings(_selected(template, {"refined": model(0.0)}, {"refined": error}, unstable_rate=1.0,
                                            hold=40.0, noise_floor=floor, noise_ratio=defaults.selection_warn_noise_ratio,
                                            noise_margin=defaults.selection_warn_noise_margin))

    assert far(4.34, 1.83) == []
    assert len(far(4.86, 1.85)) == 1
    assert far(0.04, 0.0) == []  # clean records: the margin
    assert len(far(0.38, 0.0)) == 1  # clean records far outside the clean targets
    (warning,) = far(7.2, 1.84)
    assert warning.startswith("the model reproduces the records far worse than their noise explains (free-run "
                              "error 7.2 % where the noise alone leaves 1.84 %)")
    (warning,) = far(6.72, 0.0)  # the saturation plant's clean fit
    assert "6.72 %" in warning
    assert far(7.2, None) == []  # no floor given: no such check
    # not as well as the hold's: the hold's warning says it
    assert len(far(50.0, 1.8)) == 1
    # on noisy records a candidate from before the refinement (vendor-c seed 2 at 40 dB: the trained
    # backbone, 2.80 / 2.91 % at 1.39x its floor, where nothing else warned) is a caution of its own;
    # on clean records (refinement not expected to win) a re-fit is chosen on its merits
    def before(chosen, expected):
        return selection_warnings(_selected(template, {chosen: model(0.0)}, {chosen: 2.534}, unstable_rate=1.0,
                                            hold=40.0, noise_floor=1.82, noise_ratio=3.0, noise_margin=0.5,
                                            refinement_expected=expected))

    (warning,) = before("trained backbone", True)
    assert warning.startswith("the model is the trained backbone, from before the explicit model's refinement")
    assert len(before("re-fit +100 %", True)) == 1
    assert before("pruned +0.1 % x2 from noise-compensated backbone", True) == []
    assert before("trained backbone", False) == [] and before("re-fit +100 %", False) == []
    # models without a selection (baselines, older files) have none
    assert selection_warnings(model(0.0)) == [] and selection_warnings(None) == []


def test_reference_points_add_one_point_per_operating_point_of_the_small_signal_records(train, small):
    from pisml_ros.data.dataset import steady_start_mean
    from pisml_ros.ident.backbone import reference_points

    own = reference_points(train, limit=3)
    assert len(own) == 3 and [p["inputs"][0] for p in own] == sorted(p["inputs"][0] for p in own)
    both = reference_points(train, limit=3, also=small)
    # the small-signal records all sit at one operating point: one more point, their mean rest state
    assert len({tuple(tr.u[0]) for tr in small}) == 1
    added = [p for p in both if p not in own]
    assert len(both) == 4 and len(added) == 1 and np.allclose(added[0]["inputs"], small.trajectories[0].u[0])
    assert added[0]["smallsignal"] and not any("smallsignal" in p for p in own)
    rests = [steady_start_mean(tr)[1] for tr in small]
    np.testing.assert_allclose(added[0]["state"], np.mean(rests, axis=0), rtol=1e-12)
    assert [p["inputs"][0] for p in both] == sorted(p["inputs"][0] for p in both)


def test_hold_error_is_the_error_of_holding_each_records_first_state(plant):
    from pisml_ros.ident.estimators import hold_error, training_error

    records = generate(plant, *schedules_for("train", seed=0, n_traj=3, duration=0.02))
    # a model whose field is zero holds every state: it scores exactly the hold error
    frozen = ExplicitModel(STATE_NAMES, INPUT_NAMES, ["1"], np.zeros((1, 13)))
    assert hold_error(records) == pytest.approx(training_error(frozen, records), rel=1e-9)
    assert 5.0 < hold_error(records) < 100.0


def test_selection_tolerance_counts_from_the_noise_floor_on_noisy_records():
    """``selection_floor_tolerance``: on noisy records a pruned model is near the refined one where
    its score above the records' noise floor is within (1 + τ) of the refined model's, not where
    its whole score is within ``selection_tolerance``; a tolerance given outright (the preliminary
    model's 0) and clean records (no floor) keep the whole-score rule."""
    from pisml_ros.ident.selection import _configured_selection, _selected

    def model(nonzero):
        coef = np.zeros((6, 1))
        coef[:nonzero] = 1.0
        return ExplicitModel(("x",), ("u",), ["1", "x", "u", "x**2", "x*u", "u**2"], coef, {})

    candidates = {"refined": model(6), "pruned +0.1 %": model(5), "pruned +0.1 % x2": model(3)}
    # floor 1.6 %: the refined model's own share 0.6 %, round 1's 0.9 %, round 2's 1.57 % (2.6x)
    scores = {"refined": 2.2, "pruned +0.1 %": 2.5, "pruned +0.1 % x2": 3.17}

    def chosen(**kwargs):
        return _selected(candidates["refined"], candidates, scores, tolerance=0.5, **kwargs).metadata["selection"]

    assert chosen()["chosen"] == "pruned +0.1 % x2"  # 3.17 <= 1.5 x 2.2
    above = chosen(tolerance_floor=1.6, floor_tolerance=1.0)
    assert above["chosen"] == "pruned +0.1 %"  # the cut: 1.6 + 2 x 0.6 = 2.8 %
    assert above["tolerance_floor_pct"] == 1.6 and above["floor_tolerance"] == 1.0
    assert chosen(tolerance_floor=1.6)["chosen"] == "pruned +0.1 % x2"  # floor_tolerance inf: off
    assert chosen(floor_tolerance=1.0)["chosen"] == "pruned +0.1 % x2"  # no floor (clean records)
    assert chosen(tolerance_floor=1.6, floor_tolerance=2.0)["chosen"] == "pruned +0.1 % x2"  # 1.6 + 3 x 0.6 = 3.4 %
    cfg = IdentConfig()
    assert cfg.selection_floor_tolerance == 2.0  # (the default since stop 77; 1.0 from stop 70)
    configured = _configured_selection(candidates["refined"], candidates, scores, cfg, {}, np.inf, tolerance_floor=1.6)
    assert configured.metadata["selection"]["chosen"] == "pruned +0.1 % x2"
    scores_far = dict(scores, **{"pruned +0.1 % x2": 3.5})  # 3.2x the refined model's share: beyond the cut
    assert _configured_selection(candidates["refined"], candidates, scores_far, cfg, {}, np.inf,
                                 tolerance_floor=1.6).metadata["selection"]["chosen"] == "pruned +0.1 %"
    assert _configured_selection(candidates["refined"], candidates, scores, cfg, {}, np.inf,
                                 tolerance=0.0, tolerance_floor=1.6).metadata["selection"]["chosen"] == "refined"
    with pytest.raises(ConfigError, match="selection_floor_tolerance"):
        IdentConfig.from_mapping({"selection_floor_tolerance": -1})


def test_selection_passes_over_a_model_whose_slow_mode_barely_decays_at_the_smallsignal_point():
    """``selection_decay_margin``: on noisy records a choice whose slowest mode at the small-signal
    records' rest point decays slower than the margin gives way to the candidates within the floor
    tolerance of the best score that decay at least that fast there (stop 75, protocol recording 1:
    -0.028 1/s at ug 0.8 where the plant is at -0.73)."""
    from pisml_ros.ident.selection import _configured_selection, _selected

    def model(rate, extra=0):  # x' = rate (ug - x): the equilibrium x = ug, its mode at -rate
        coef = np.zeros((2 + extra, 1))
        coef[:2, 0] = [rate, -rate]
        coef[2:, 0] = 1e-9  # coefficients that do nothing at rest, so that the models differ in size
        return ExplicitModel(("x",), ("ug",), ["ug", "x", "x**3", "ug**3", "x*ug"][:2 + extra], coef, {})

    points = [{"inputs": [0.8], "state": [0.8], "smallsignal": True}, {"inputs": [1.0], "state": [1.0]}]
    template = ExplicitModel(("x",), ("ug",), ["ug", "x"], np.zeros((2, 1)), {"reference_points": points})
    candidates = {"refined": model(0.03, 3), "pruned +0.1 % x3": model(0.03),
                  "pruned +0.1 % at long windows": model(0.5, 2), "pruned +0.1 % x2 at long windows": model(0.5, 1)}
    scores = {"refined": np.inf, "pruned +0.1 % x3": 2.8, "pruned +0.1 % at long windows": 3.3,
              "pruned +0.1 % x2 at long windows": 2.9}
    noisy = {"tolerance": 0.5, "unstable_rate": 1.0, "tolerance_floor": 1.8, "floor_tolerance": 1.0}

    def chosen(scores=scores, template=template, **kwargs):
        return _selected(template, candidates, scores, **{**noisy, **kwargs}).metadata["selection"]

    assert chosen()["chosen"] == "pruned +0.1 % x3" and chosen()["decay_rechoice"] is None  # margin 0: off
    assert chosen()["smallsignal_rate"] is None and not chosen()["warnings"]
    moved = chosen(decay_margin=0.1)
    assert moved["smallsignal_rate"] == pytest.approx(-0.5) and not moved["warnings"]
    # the cut: 1.8 + 2 x (2.8 - 1.8) = 3.8 %; among those decaying fast enough the best, then its
    # family's sparsest near it
    assert moved["chosen"] == "pruned +0.1 % x2 at long windows" and moved["decay_margin"] == 0.1
    rechoice = moved["decay_rechoice"]
    assert rechoice["from"] == "pruned +0.1 % x3" and rechoice["to"] == moved["chosen"]
    assert rechoice["rates"]["pruned +0.1 % x3"] == pytest.approx(-0.03)
    assert rechoice["rates"]["pruned +0.1 % x2 at long windows"] == pytest.approx(-0.5)
    assert chosen(decay_margin=0.02)["chosen"] == "pruned +0.1 % x3"  # decays fast enough
    # none that decays fast enough scores within the cut: the choice stands
    far = {**scores, "pruned +0.1 % at long windows": 3.9, "pruned +0.1 % x2 at long windows": 4.0}
    stands = chosen(far, decay_margin=0.1)
    assert stands["chosen"] == "pruned +0.1 % x3" and stands["smallsignal_rate"] == pytest.approx(-0.03)
    # ... and the model says so (one warning: the slow mode, nothing else is wrong with it)
    assert len(stands["warnings"]) == 1 and "decays at only 0.03 1/s" in stands["warnings"][0]
    # clean records (no floor) and records without a small-signal rest point: no such rule
    assert chosen(decay_margin=0.1, tolerance_floor=None)["chosen"] == "pruned +0.1 % x3"
    at_rest = ExplicitModel(("x",), ("ug",), ["ug", "x"], np.zeros((2, 1)),
                            {"reference_points": [dict(points[0], smallsignal=False), points[1]]})
    assert chosen(template=at_rest, decay_margin=0.1)["chosen"] == "pruned +0.1 % x3"
    # nor does it lose an operating point the choice has as stable: x' = 1.2 - ug - x**2 decays fast
    # (-1.26 1/s at ug 0.8) but has no equilibrium above ug 1.2
    folding = ExplicitModel(("x",), ("ug",), ["1", "ug", "x**2"], np.array([[1.2], [-1.0], [-1.0]]), {})
    candidates["pruned +0.1 % x2 at long windows"] = folding
    assert chosen(decay_margin=0.1, equilibrium_grid=(0.8, 1.0))["chosen"] == "pruned +0.1 % x2 at long windows"
    assert chosen(decay_margin=0.1, equilibrium_grid=(0.8, 1.3))["chosen"] == "pruned +0.1 % at long windows"
    candidates["pruned +0.1 % at long windows"] = folding
    assert chosen(decay_margin=0.1, equilibrium_grid=(0.8, 1.3))["chosen"] == "pruned +0.1 % x3"
    candidates["pruned +0.1 % at long windows"] = candidates["pruned +0.1 % x2 at long windows"] = model(0.5, 1)
    cfg = IdentConfig()
    assert cfg.selection_decay_margin == 0.1  # (the default since stop 75)
    configured = _configured_selection(template, candidates, scores, cfg, {}, np.inf, tolerance_floor=1.8)
    assert configured.metadata["selection"]["chosen"] == "pruned +0.1 % x2 at long windows"
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="selection_decay_margin"):
            IdentConfig.from_mapping({"selection_decay_margin": bad})


def test_selection_passes_over_a_model_unstable_where_no_record_rests():
    """``selection_stability_rechoice``: on noisy records a choice unstable at a grid voltage below
    every rest point gives way to the candidates within the floor tolerance of the best score that are
    stable there, keep the choice's operating points and decay at the small-signal point as fast
    (stop 100, 40 dB: recordings 347, 356 and 378 chose models unstable at ug 0.2-0.6, where the
    plant decays at -0.22 1/s and no record rests)."""
    from pisml_ros.ident.selection import _below_rests, _configured_selection, _selected

    def model(c0, c1, extra=0):  # x' = (c0 + c1 ug)(ug - x): the equilibrium x = ug, its mode at -(c0 + c1 ug)
        coef = np.zeros((4 + extra, 1))
        coef[:4, 0] = [c0, -c0, c1, -c1]
        coef[4:, 0] = 1e-9  # coefficients that do nothing at rest, so that the models differ in size
        return ExplicitModel(("x",), ("ug",), ["ug", "x", "ug**2", "x*ug", "x**3", "ug**3"][:4 + extra], coef, {})

    points = [{"inputs": [0.8], "state": [0.8], "smallsignal": True}, {"inputs": [1.0], "state": [1.0]}]
    template = ExplicitModel(("x",), ("ug",), ["ug", "x"], np.zeros((2, 1)), {"reference_points": points})
    grid = (0.2, 0.4, 0.8, 1.0)
    assert _below_rests(template, grid) == [0, 1] and _below_rests(template, (0.8, 1.2)) == []
    # the choice: -0.3 1/s at ug 0.8, +0.1 at 0.4, +0.3 at 0.2; the others -0.5 everywhere
    candidates = {"refined": model(-0.5, 1.0, 2), "pruned +0.1 % x3": model(-0.5, 1.0),
                  "pruned +0.1 % at long windows": model(0.5, 0.0, 2),
                  "pruned +0.1 % x2 at long windows": model(0.5, 0.0, 1)}
    scores = {"refined": np.inf, "pruned +0.1 % x3": 2.8, "pruned +0.1 % at long windows": 3.3,
              "pruned +0.1 % x2 at long windows": 2.9}
    noisy = {"tolerance": 0.5, "unstable_rate": 1.0, "tolerance_floor": 1.8, "floor_tolerance": 1.0,
             "equilibrium_grid": grid}

    def chosen(scores=scores, **kwargs):
        return _selected(template, candidates, scores, **{**noisy, **kwargs}).metadata["selection"]

    assert chosen()["chosen"] == "pruned +0.1 % x3" and chosen()["stability_rechoice"] is None  # off
    moved = chosen(stability_rechoice=True)
    # the cut: 1.8 + 2 x (2.8 - 1.8) = 3.8 %; among those stable below the rests the best, then its
    # family's sparsest near it
    assert moved["chosen"] == "pruned +0.1 % x2 at long windows"
    rechoice = moved["stability_rechoice"]
    assert rechoice["from"] == "pruned +0.1 % x3" and rechoice["to"] == moved["chosen"]
    assert rechoice["rates"]["pruned +0.1 % x3"] == pytest.approx(0.3)
    assert rechoice["rates"]["pruned +0.1 % x2 at long windows"] == pytest.approx(-0.5)
    # the model passed over stays an alternative: the analysis says the records do not decide there
    model_on = _selected(template, candidates, scores, **noisy, stability_rechoice=True)
    assert "pruned +0.1 % x3" in [entry["name"] for entry in model_on.metadata["alternatives"]]
    # none stable there within the cut, clean records (no floor), a grid with no voltage below the
    # rests: the choice stands
    far = {**scores, "pruned +0.1 % at long windows": 3.9, "pruned +0.1 % x2 at long windows": 4.0}
    assert chosen(far, stability_rechoice=True)["chosen"] == "pruned +0.1 % x3"
    assert chosen(stability_rechoice=True, tolerance_floor=None)["chosen"] == "pruned +0.1 % x3"
    assert chosen(stability_rechoice=True, equilibrium_grid=(0.8, 1.0))["chosen"] == "pruned +0.1 % x3"
    # nor does it lose an operating point the choice has as stable: x' = 1.05 - ug - x**2 is stable
    # at ug 0.2-1.0 but has no equilibrium above ug 1.05, where the choice is stable (-0.7 1/s at 1.2)
    folding = ExplicitModel(("x",), ("ug",), ["1", "ug", "x**2"], np.array([[1.05], [-1.0], [-1.0]]), {})
    candidates["pruned +0.1 % x2 at long windows"] = folding
    assert chosen(stability_rechoice=True)["chosen"] == "pruned +0.1 % x2 at long windows"
    assert chosen(stability_rechoice=True, equilibrium_grid=grid + (1.2,))["chosen"] == "pruned +0.1 % at long windows"
    # nor, with the decay margin on, one that decays slower than it at the small-signal point (the
    # rule of selection_decay_margin stands)
    candidates["pruned +0.1 % x2 at long windows"] = model(0.05, 0.0, 1)
    assert chosen(stability_rechoice=True)["chosen"] == "pruned +0.1 % x2 at long windows"
    assert chosen(stability_rechoice=True, decay_margin=0.1)["chosen"] == "pruned +0.1 % at long windows"
    candidates["pruned +0.1 % x2 at long windows"] = model(0.5, 0.0, 1)
    assert IdentConfig().selection_stability_rechoice is True  # (the default since stop 100)
    on = IdentConfig.from_mapping({"selection_equilibrium_grid": list(grid)})
    configured = _configured_selection(template, candidates, scores, on, {}, np.inf, tolerance_floor=1.8)
    assert configured.metadata["selection"]["chosen"] == "pruned +0.1 % x2 at long windows"
    off = IdentConfig.from_mapping({"selection_stability_rechoice": False, "selection_equilibrium_grid": list(grid)})
    configured = _configured_selection(template, candidates, scores, off, {}, np.inf, tolerance_floor=1.8)
    assert configured.metadata["selection"]["chosen"] == "pruned +0.1 % x3"


def test_selection_passes_over_a_prune_round_that_lost_the_fit_and_the_rounds_after_it():
    from pisml_ros.ident.selection import _lost_rounds, _selected

    def model(nonzero):
        coef = np.zeros((6, 1))
        coef[:nonzero] = 1.0
        return ExplicitModel(("x",), ("u",), ["1", "x", "u", "x**2", "x*u", "u**2"], coef, {})

    candidates = {"refined": model(6), "pruned +0.1 %": model(5), "pruned +0.1 % x2": model(3),
                  "pruned +0.1 % x3": model(2)}
    # round 2 scores 1.6x round 1 (it dropped a term the records need); round 3, pruned from it,
    # is within the tolerance of the refined model and would be the sparsest near it
    scores = {"refined": 0.033, "pruned +0.1 %": 0.030, "pruned +0.1 % x2": 0.048, "pruned +0.1 % x3": 0.040}
    assert _selected(candidates["refined"], candidates, scores, tolerance=0.5).metadata["selection"][
        "chosen"] == "pruned +0.1 % x3"
    selection = _selected(candidates["refined"], candidates, scores, tolerance=0.5, round_rise=0.35).metadata[
        "selection"]
    assert selection["chosen"] == "pruned +0.1 %"
    assert selection["lost_rounds"] == ["pruned +0.1 % x2", "pruned +0.1 % x3"] and selection["round_rise"] == 0.35
    # a round that rose less than that is sound, and so are the rounds after it
    sound = dict(scores, **{"pruned +0.1 % x2": 0.038})
    assert _selected(candidates["refined"], candidates, sound, tolerance=0.5, round_rise=0.35).metadata[
        "selection"]["chosen"] == "pruned +0.1 % x3"
    # rounds are judged within their own start's family; a round after an unscored (inf) one is not judged
    families = {"pruned +0.1 %": 1.0, "pruned +0.1 % x2": 1.2, "pruned +0.1 % x3": 2.0,
                "pruned +0.1 % from distilled": np.inf, "pruned +0.1 % x2 from distilled": 3.0,
                "pruned +0.1 % x3 from distilled": 3.1, "pruned +0.1 % with growing prior": 1.0,
                "pruned +0.1 % x2 with growing prior": 1.5, "pruned +0.1 % x3 with growing prior": 1.0}
    assert _lost_rounds(families, 0.35) == {"pruned +0.1 % x3", "pruned +0.1 % x2 with growing prior",
                                           "pruned +0.1 % x3 with growing prior"}
    assert _lost_rounds(families, np.inf) == set()
    # a round whose free run blew up is lost too
    assert _lost_rounds({"pruned +0.1 %": 1.0, "pruned +0.1 % x2": np.inf}, 0.35) == {"pruned +0.1 % x2"}
    # a lost round that scores best of all still wins: the rule keeps lost rounds from standing in
    # for the best, not the best from winning (here round 3 recovered below round 1 after round 2
    # had lost the fit; without the exception round 1, at twice the best score, would be taken)
    recovered = {"refined": 0.090, "pruned +0.1 %": 0.030, "pruned +0.1 % x2": 0.045, "pruned +0.1 % x3": 0.015}
    selection = _selected(candidates["refined"], candidates, recovered, tolerance=0.5, round_rise=0.35).metadata[
        "selection"]
    assert selection["chosen"] == "pruned +0.1 % x3" and "pruned +0.1 % x3" in selection["lost_rounds"]


def test_selection_prefers_the_sparsest_pruned_model_near_the_refined_one():
    from pisml_ros.ident.selection import _selected

    def model(nonzero):
        coef = np.zeros((6, 1))
        coef[:nonzero] = 1.0
        return ExplicitModel(("x",), ("u",), ["1", "x", "u", "x**2", "x*u", "u**2"], coef, {})

    candidates = {"backbone": model(6), "refined": model(6), "pruned +0.1 %": model(5), "pruned +0.3 %": model(3),
                  "pruned +1 %": model(2)}
    # a pruned model slightly better than the refined one does not narrow the tolerance: +0.3 %
    # (within 1.5x of the refined error) is chosen, +1 % (beyond it) is not
    scores = {"backbone": 1.0, "refined": 0.033, "pruned +0.1 %": 0.029, "pruned +0.3 %": 0.044, "pruned +1 %": 0.055}
    chosen = _selected(candidates["refined"], candidates, scores, tolerance=0.5)
    assert chosen.metadata["selection"]["chosen"] == "pruned +0.3 %"
    assert chosen.n_parameters == 3
    # a pruned model whose stability at the records' operating points differs from the refined
    # model's is passed over for one that keeps it: the refined dx/dt = 1 - x + 0.01 u is stable, the
    # sparsest pruned one (dx/dt = x - 1) is not
    template = ExplicitModel(("x",), ("u",), ["1", "x", "u"], np.zeros((3, 1)),
                             {"reference_points": [{"inputs": [0.0], "state": [1.0]}]})
    two = {"refined": ExplicitModel(("x",), ("u",), ["1", "x", "u"], np.array([[1.0], [-1.0], [0.01]]), {}),
           "pruned +0.3 %": ExplicitModel(("x",), ("u",), ["1", "x"], np.array([[1.0], [-1.0]]), {}),
           "pruned +1 %": ExplicitModel(("x",), ("u",), ["1", "x"], np.array([[-1.0], [1.0]]), {})}
    scores2 = {"refined": 0.03, "pruned +0.3 %": 0.04, "pruned +1 %": 0.035}
    assert _selected(template, two, scores2, tolerance=0.5).metadata["selection"]["chosen"] == "pruned +0.3 %"
    # ... and where the refined model is unstable there (a record may start at a weakly unstable
    # equilibrium), a stable pruned model is not preferred for it
    two["refined"] = ExplicitModel(("x",), ("u",), ["1", "x", "u"], np.array([[-1.0], [1.0], [0.01]]), {})
    assert _selected(template, two, scores2, tolerance=0.5).metadata["selection"]["chosen"] == "pruned +1 %"
    # ... but a refined model that contradicts the record at rest there (a mode growing at 10 1/s,
    # beyond unstable_rate) has no verdicts to copy: the sparsest pruned model (dx/dt = 1 - x) wins
    # over one that is weakly unstable like it (dx/dt = 0.5 (x - 1) + 0.001 u)
    copied = {"refined": ExplicitModel(("x",), ("u",), ["1", "x", "u"], np.array([[-10.0], [10.0], [0.01]]), {}),
              "pruned +0.3 %": ExplicitModel(("x",), ("u",), ["1", "x", "u"], np.array([[-0.5], [0.5], [0.001]]), {}),
              "pruned +1 %": ExplicitModel(("x",), ("u",), ["1", "x"], np.array([[1.0], [-1.0]]), {})}
    picked = _selected(template, copied, scores2, tolerance=0.5, unstable_rate=1.0).metadata["selection"]
    assert picked["inconsistent_rest_points"]["refined"] == 1 and picked["chosen"] == "pruned +1 %"
    # ... nor is its score the tolerance's yardstick: run freely it leaves the rest state, and its
    # large error would let any pruned model count as near (here the sparsest, at 6.7x the best)
    runaway = {"refined": copied["refined"],
               "pruned +0.1 %": ExplicitModel(("x",), ("u",), ["1", "x", "u"], np.array([[1.0], [-1.0], [0.01]]), {}),
               "pruned +1 %": ExplicitModel(("x",), ("u",), ["1", "x"], np.array([[1.0], [-1.0]]), {})}
    runaway_scores = {"refined": 1.0, "pruned +0.1 %": 0.03, "pruned +1 %": 0.2}
    assert _selected(template, runaway, runaway_scores, tolerance=0.5, unstable_rate=1.0).metadata["selection"][
        "chosen"] == "pruned +0.1 %"
    # ... an infinite score (a free run that blew up) is no yardstick either
    runaway_scores["refined"] = np.inf
    assert _selected(template, runaway, runaway_scores, tolerance=0.5, unstable_rate=1.0).metadata["selection"][
        "chosen"] == "pruned +0.1 %"
    runaway_scores["pruned +1 %"] = 0.04  # within 1.5x of the best eligible score: the sparser one wins
    assert _selected(template, runaway, runaway_scores, tolerance=0.5, unstable_rate=1.0).metadata["selection"][
        "chosen"] == "pruned +1 %"
    # where a re-choice runs over some of the competing candidates only, a refined model that
    # competes stays the yardstick even outside them
    from pisml_ros.ident.selection import _chosen_among

    consistent = dict(runaway, refined=two["refined"])
    subset = ["pruned +0.1 %", "pruned +1 %"]
    subset_scores = {"refined": 0.2, "pruned +0.1 %": 0.03, "pruned +1 %": 0.2}
    assert _chosen_among(subset, consistent, subset_scores, 0.5, [], {}) == "pruned +0.1 %"
    assert _chosen_among(subset, consistent, subset_scores, 0.5, [], {}, competing=["refined", *subset]) == "pruned +1 %"
    # a candidate with no equilibrium at the records' operating points (dx/dt = 1 - 0.5 u never
    # vanishes at u = 0) does not win, however well it scores
    two["re-fit +300 %"] = ExplicitModel(("x",), ("u",), ["1", "u"], np.array([[1.0], [-0.5]]), {})
    scores2["re-fit +300 %"] = 0.001
    assert _selected(template, two, scores2, tolerance=0.5).metadata["selection"]["chosen"] == "pruned +1 %"
    # ... nor one whose equilibrium there has a mode growing faster than the selection's rate (dx/dt
    # = 5x - 5 + 0.01 u: +5 1/s), when another candidate is consistent with the record at rest
    fast = dict(two, **{"backbone": ExplicitModel(("x",), ("u",), ["1", "x", "u"], np.array([[-5.0], [5.0], [0.01]]), {})})
    fast_scores = dict(scores2, backbone=0.001)
    assert _selected(template, fast, fast_scores, tolerance=0.5).metadata["selection"]["chosen"] == "backbone"
    chosen = _selected(template, fast, fast_scores, tolerance=0.5, unstable_rate=1.0)
    assert chosen.metadata["selection"]["chosen"] == "pruned +1 %"
    assert chosen.metadata["selection"]["inconsistent_rest_points"]["backbone"] == 1
    # ... nor one with a state whose equation has no term (y frozen: no isolated equilibrium, a zero
    # eigenvalue everywhere), however well it scores
    template_xy = ExplicitModel(("x", "y"), ("u",), ["1", "x", "y"], np.zeros((3, 2)),
                                {"reference_points": [{"inputs": [0.0], "state": [1.0, 0.0]}]})
    frozen = {"refined": ExplicitModel(("x", "y"), ("u",), ["1", "x", "y"], np.array([[1.0, 0], [-1, 0.5], [0.2, -1]]), {}),
              "pruned +1 %": ExplicitModel(("x", "y"), ("u",), ["1", "x", "y"], np.array([[1.0, 0], [-1, 0], [0.2, 0]]), {})}
    selection = _selected(template_xy, frozen, {"refined": 0.05, "pruned +1 %": 0.01}, tolerance=0.5).metadata["selection"]
    assert selection["chosen"] == "refined" and selection["inconsistent_rest_points"] == {"refined": 0, "pruned +1 %": 1}
    # the refinement starts from the best merged or re-fitted model with those equilibria, and from
    # the noise-compensated backbone where it has them
    from pisml_ros.ident.estimators import _refinement_starts

    points = template.metadata["reference_points"]
    starts = {"backbone": two["refined"], "distilled": two["pruned +1 %"], "re-fit +300 %": two["re-fit +300 %"],
              "re-fit +100 %": two["pruned +0.3 %"]}
    start_scores = {"backbone": 0.0001, "distilled": 0.5, "re-fit +300 %": 0.001, "re-fit +100 %": 0.2}
    assert _refinement_starts(starts, start_scores, points) == ["re-fit +100 %"]
    start_scores["re-fit +100 %"] = float("inf")
    assert _refinement_starts(starts, start_scores, points) == ["distilled"]
    starts["noise-compensated backbone"], start_scores["noise-compensated backbone"] = two["refined"], 0.3
    assert _refinement_starts(starts, start_scores, points) == ["distilled", "noise-compensated backbone"]
    starts["noise-compensated backbone"] = two["re-fit +300 %"]  # no equilibrium: not a start
    assert _refinement_starts(starts, start_scores, points) == ["distilled"]
    # a re-fit whose free run is further off than zero (>= 100 %) is no start, even where the merged
    # model lacks an equilibrium; where every candidate is that far off, the merged model is (stop 98:
    # from the 337 % re-fit that had the equilibria the whole fit failed); without one the equilibria decide
    hopeless = {"distilled": two["re-fit +300 %"], "re-fit +100 %": two["pruned +1 %"]}
    assert _refinement_starts(hopeless, {"distilled": 6.8, "re-fit +100 %": 276.0}, points) == ["distilled"]
    assert _refinement_starts(hopeless, {"distilled": 99.0, "re-fit +100 %": 20.0}, points) == ["re-fit +100 %"]
    assert _refinement_starts(hopeless, {"distilled": float("inf"), "re-fit +100 %": 337.0}, points) == ["distilled"]
    refits = {"re-fit +300 %": two["re-fit +300 %"], "re-fit +100 %": two["pruned +1 %"]}
    assert _refinement_starts(refits, {"re-fit +300 %": 150.0, "re-fit +100 %": 276.0}, points) == ["re-fit +100 %"]
    # each start's refinement is a family of its own: the pruned models compete with their own refined model
    family = {"refined": model(6), "pruned +0.3 %": model(3), "refined from noise-compensated backbone": model(6),
              "pruned +0.3 % from noise-compensated backbone": model(2)}
    family_scores = {"refined": 0.05, "pruned +0.3 %": 0.06, "refined from noise-compensated backbone": 0.03,
                     "pruned +0.3 % from noise-compensated backbone": 0.2}
    assert _selected(candidates["refined"], family, family_scores, tolerance=0.5).metadata["selection"]["chosen"] \
        == "refined from noise-compensated backbone"
    family_scores["pruned +0.3 % from noise-compensated backbone"] = 0.04
    assert _selected(candidates["refined"], family, family_scores, tolerance=0.5).metadata["selection"]["chosen"] \
        == "pruned +0.3 % from noise-compensated backbone"
    # a later prune round ("… xR") belongs to the family of its start
    from pisml_ros.ident.selection import _refinement_family

    assert _refinement_family("pruned +0.3 % x2") == "" and \
        _refinement_family("pruned +0.3 % x3 from noise-compensated backbone") == " from noise-compensated backbone"
    family["pruned +0.3 % x2 from noise-compensated backbone"] = model(1)
    family_scores["pruned +0.3 % x2 from noise-compensated backbone"] = 0.044
    assert _selected(candidates["refined"], family, family_scores, tolerance=0.5).metadata["selection"]["chosen"] \
        == "pruned +0.3 % x2 from noise-compensated backbone"
    # where another candidate wins, pruned models do not come back through the tolerance
    scores["backbone"] = 0.02
    assert _selected(candidates["refined"], candidates, scores, tolerance=0.5).metadata["selection"]["chosen"] == "backbone"


def test_second_refinement_start_runs_only_where_the_first_family_fails():
    """refine_starts=fallback: the noise-compensated backbone's refinement is needed where the
    selection over the first start's family takes another candidate, or one of the family that is
    inconsistent with a point where the records sat at rest."""
    from pisml_ros.ident.selection import _refinement_suffices

    template = ExplicitModel(("x",), ("u",), ["1", "x", "u"], np.zeros((3, 1)),
                             {"reference_points": [{"inputs": [0.0], "state": [1.0]}]})
    stable = ExplicitModel(("x",), ("u",), ["1", "x", "u"], np.array([[1.0], [-1.0], [0.01]]), {})  # x* = 1, -1 1/s
    growing = ExplicitModel(("x",), ("u",), ["1", "x", "u"], np.array([[-5.0], [5.0], [0.01]]), {})  # +5 1/s
    cfg = IdentConfig()
    candidates = {"distilled": stable, "refined": stable, "pruned +0.1 %": stable}
    scores = {"distilled": 1.0, "refined": 0.03, "pruned +0.1 %": 0.035}
    assert _refinement_suffices(template, candidates, scores, cfg, {})
    # the family lost to a candidate before the refinement
    assert not _refinement_suffices(template, candidates, dict(scores, distilled=0.01), cfg, {})
    # the family won, but only with models growing at the rest point (+5 1/s > selection_unstable_rate)
    bad = {"distilled": growing, "refined": growing, "pruned +0.1 %": growing}
    assert not _refinement_suffices(template, bad, scores, cfg, {})


def test_integrator_equations_keep_the_constant_and_plain_signals_only():
    from pisml_ros.ident.library import integrator_row_mask

    terms = ["1", "il_d", "2*vc_q", "Pf*vc_q", "vc_d*ig_d + vc_q*ig_q", "ug*cos(theta_g - delta)", "ig_d**2"]
    mask = integrator_row_mask(terms, STATE_NAMES, STATE_NAMES + INPUT_NAMES, SignalRoles())
    integrators = [STATE_NAMES.index(s) for s in ("phi_d", "phi_q", "gamma_d", "gamma_q")]
    others = [j for j in range(len(STATE_NAMES)) if j not in integrators]
    assert mask[:, others].all()
    assert mask[:3, integrators].all() and not mask[3:, integrators].any()
    none = integrator_row_mask(terms, STATE_NAMES, STATE_NAMES + INPUT_NAMES, SignalRoles(integrators=()))
    assert none.all()


def test_integrator_equations_without_their_own_loop():
    from pisml_ros.ident.library import integrator_row_mask

    assert SignalRoles().integrator_loops() == [("phi_d", "phi_q"), ("gamma_d", "gamma_q")]
    assert SignalRoles(integrators=("a", "b", "c")).integrator_loops() == [("a",), ("b",), ("c",)]
    terms = ["1", "phi_d", "phi_q", "gamma_d", "gamma_q", "vc_d"]
    index = {name: STATE_NAMES.index(name) for name in ("phi_d", "phi_q", "gamma_d", "gamma_q", "vc_d")}
    kept = integrator_row_mask(terms, STATE_NAMES, STATE_NAMES + INPUT_NAMES, SignalRoles())
    assert kept.all()
    mask = integrator_row_mask(terms, STATE_NAMES, STATE_NAMES + INPUT_NAMES, SignalRoles(), own_loop=False)
    # the voltage loop's rows lose phi_d, phi_q and keep gamma (none in the plant, but not ruled out)
    for row in ("phi_d", "phi_q"):
        assert list(mask[:, index[row]]) == [True, False, False, True, True, True]
    # the current loop's rows keep the outer loop's integrators (KiV·phi inside the current reference)
    for row in ("gamma_d", "gamma_q"):
        assert list(mask[:, index[row]]) == [True, True, True, False, False, True]
    # other rows keep every integrator
    assert mask[:, index["vc_d"]].all()
    # "cascade": the voltage loop's rows lose the current loop's integrators too, the current loop's
    # rows are as above
    cascade = integrator_row_mask(terms, STATE_NAMES, STATE_NAMES + INPUT_NAMES, SignalRoles(), own_loop=False,
                                  inner_loops=False)
    for row in ("phi_d", "phi_q"):
        assert list(cascade[:, index[row]]) == [True, False, False, False, False, True]
    for row in ("gamma_d", "gamma_q", "vc_d"):
        assert (cascade[:, index[row]] == mask[:, index[row]]).all()
    # one loop per integrator (an odd count): each row loses itself and those listed after it
    odd = integrator_row_mask(["1", "phi_d", "phi_q", "gamma_d"], STATE_NAMES, STATE_NAMES + INPUT_NAMES,
                              SignalRoles(integrators=("phi_d", "phi_q", "gamma_d")), own_loop=False, inner_loops=False)
    assert list(odd[:, index["phi_d"]]) == [True, False, False, False]
    assert list(odd[:, index["phi_q"]]) == [True, True, False, False]
    assert list(odd[:, index["gamma_d"]]) == [True, True, True, False]


def test_filter_equations_keep_the_physics_of_a_rotating_frame_only():
    from pisml_ros.ident.library import filter_row_mask

    terms = ["1", "il_d", "Pf*vc_q", "Pf*vc_d", "Pf*ig_q", "Pf*ig_d", "ug*sin(delta - theta_g)",
             "ug*cos(theta_g - delta)", "ig_d**2", "vc_d*ig_d + vc_q*ig_q", "sin(delta)", "Pf", "ug", "gamma_d"]
    mask = filter_row_mask(terms, STATE_NAMES, STATE_NAMES + INPUT_NAMES, SignalRoles())

    def allowed(state):
        return [t for t, keep in zip(terms, mask[:, STATE_NAMES.index(state)]) if keep]

    grid = ["ug*sin(delta - theta_g)", "ug*cos(theta_g - delta)"]
    # each row keeps the dq signals, the grid terms and the frame coupling with its own pair's
    # other axis only (no power or controller state, no input alone)
    assert allowed("vc_d") == ["1", "il_d", "Pf*vc_q", *grid]
    assert allowed("vc_q") == ["1", "il_d", "Pf*vc_d", *grid]
    assert allowed("ig_d") == ["1", "il_d", "Pf*ig_q", *grid]
    assert allowed("ig_q") == ["1", "il_d", "Pf*ig_d", *grid]
    # the converter-side current (the vendor's control acts there) and the other rows keep everything
    for state in ("il_d", "il_q", "Pf", "delta", "gamma_d"):
        assert allowed(state) == terms
    # without a frequency role no coupling is physics
    no_frequency = filter_row_mask(terms, STATE_NAMES, STATE_NAMES + INPUT_NAMES, SignalRoles(frequency=None))
    assert [t for t, keep in zip(terms, no_frequency[:, STATE_NAMES.index("ig_d")]) if keep] == ["1", "il_d", *grid]
    with pytest.raises(ConfigError, match="filter_terms must be physics or any, got 'linear'"):
        IdentConfig.from_mapping({"filter_terms": "linear"})


def test_physics_filter_start_drops_cancelling_terms_and_keeps_the_starts_field_on_the_records(plant, train):
    from pisml_ros.ident.estimators import _integrators_restricted

    terms = physics_library(SignalRoles(), STATE_NAMES, coupling=True)
    backbone = fit_backbone(train, terms)
    row, k1, k2 = STATE_NAMES.index("ig_d"), terms.index("Pf*ig_d"), terms.index("Pf*il_d")
    coef = backbone.coefficients.copy()
    coef[k1, row] += 500.0  # a pair that cancels at the records' currents (il ≈ ig)
    coef[k2, row] -= 500.0
    start = ExplicitModel(backbone.state_names, backbone.input_names, terms, coef)
    restricted = _integrators_restricted(start, IdentConfig.from_mapping({"filter_terms": "physics"}), train)
    kept = [t for t, c in zip(terms, restricted.coefficients[:, row]) if c != 0]
    assert set(kept) <= {"1", "il_d", "il_q", "vc_d", "vc_q", "ig_d", "ig_q", "ug*cos(theta_g - delta)",
                         "ug*sin(theta_g - delta)", "Pf*ig_q"} and "vc_d" in kept
    assert restricted.metadata["filter_terms"] == "physics"
    # the rows outside the filter are the start's
    others = [j for j, s in enumerate(STATE_NAMES) if s not in ("vc_d", "vc_q", "ig_d", "ig_q")]
    assert np.array_equal(restricted.coefficients[:, others],
                          _integrators_restricted(start, IdentConfig.from_mapping({"filter_terms": "any"}),
                                                  train).coefficients[:, others])
    # over the records' samples the re-fitted row is the start's field (the pair's share taken up
    # by the plain currents, Pf hardly moving there); the start with the terms only dropped is not
    x, u = np.concatenate([tr.x for tr in train]), np.concatenate([tr.u for tr in train])
    dropped = np.where(np.isin(np.array(terms)[:, None], kept) | (np.arange(13) != row)[None, :], coef, 0.0)

    def row_field(c):
        return ExplicitModel(STATE_NAMES, INPUT_NAMES, terms, c).vector_field(x, u)[:, row]

    def distance(c, reference):
        return np.linalg.norm(row_field(c) - reference) / np.linalg.norm(reference)

    started = row_field(coef)
    # (measured: 5 % against 3100 %)
    assert distance(restricted.coefficients, started) < 0.1 \
        and distance(dropped, started) > 20 * distance(restricted.coefficients, started)
    # and it is no further from the plant's row than the start
    truth = plant.vector_field(x, u)[:, row]
    # (measured: 13.7 % against the start's 14.5 %, the backbone of 20 ms records)
    assert distance(restricted.coefficients, truth) < 1.05 * distance(coef, truth)


def test_power_rows_keep_what_a_low_pass_filter_of_a_measured_power_gives_them():
    from pisml_ros.ident.library import power_row_mask

    terms = ["1", "Pf", "Qf", "delta", "phi_d", "ig_d*vc_d", "ig_d**2", "il_q*ig_d", "Pf*il_d", "il_d",
             "ug*cos(delta - theta_g)", "vc_d**3", "Pf*Qf"]
    mask = power_row_mask(terms, STATE_NAMES, STATE_NAMES + INPUT_NAMES, SignalRoles())

    def allowed(state):
        return [t for t, keep in zip(terms, mask[:, STATE_NAMES.index(state)]) if keep]

    # the constant, the row's own state and products of two dq signals (v·i and, behind a damping
    # resistor, i·i); no angle, controller state, frequency coupling, plain signal or cubic
    assert allowed("Pf") == ["1", "Pf", "ig_d*vc_d", "ig_d**2", "il_q*ig_d"]
    assert allowed("Qf") == ["1", "Qf", "ig_d*vc_d", "ig_d**2", "il_q*ig_d"]
    for state in ("delta", "phi_d", "il_d", "vc_d", "ig_d"):
        assert allowed(state) == terms
    assert power_row_mask(terms, STATE_NAMES, STATE_NAMES + INPUT_NAMES, SignalRoles(power=())).all()
    with pytest.raises(ConfigError, match="power_terms must be physics or any, got 'linear'"):
        IdentConfig.from_mapping({"power_terms": "linear"})


def test_grid_current_rows_take_the_grid_inductors_voltage_as_one_term_where_the_start_has_it(train):
    from pisml_ros.ident.estimators import _integrators_restricted
    from pisml_ros.ident.library import filter_row_mask, grid_voltage_pairs

    terms = physics_library(SignalRoles(), STATE_NAMES, coupling=True)
    signals = STATE_NAMES + INPUT_NAMES
    pairs = grid_voltage_pairs(terms, STATE_NAMES, signals, SignalRoles())
    # ig_d pairs vc_d with ug·cos(θg − δ), ig_q pairs vc_q with ug·sin(θg − δ), written as the library writes them
    assert [(STATE_NAMES[row], terms[kv], terms[kg], sign) for row, kv, kg, sign, _ in pairs] == [
        ("ig_d", "vc_d", "ug*cos(theta_g - delta)", 1.0), ("ig_q", "vc_q", "ug*sin(theta_g - delta)", 1.0)]
    # a grid term written the other way round carries its sign
    flipped = [t.replace("sin(theta_g - delta)", "sin(delta - theta_g)") for t in terms]
    assert [p[3] for p in grid_voltage_pairs(flipped, STATE_NAMES, signals, SignalRoles())] == [1.0, -1.0]

    backbone = fit_backbone(train, terms)
    # a start whose filter rows hold the physics terms only (the restriction's re-fit keeps them)
    coef = np.where(filter_row_mask(terms, STATE_NAMES, signals, SignalRoles()), backbone.coefficients, 0.0)
    for row, kv, kg, _, _ in pairs:  # the start's two coefficients 1 % apart (a fit's noise)
        coef[kv, row], coef[kg, row] = 7500.0, -7425.0
    start = ExplicitModel(STATE_NAMES, INPUT_NAMES, terms, coef)
    tied = _integrators_restricted(start, IdentConfig.from_mapping({"filter_voltage_tie": 0.05}), train)
    assert tied.metadata["filter_voltage_tie"] == ["ig_d", "ig_q"]
    for row, kv, kg, _, tie in pairs:
        assert tied.coefficients[kv, row] == 0 and tied.coefficients[kg, row] == 0
        assert tied.coefficients[tied.terms.index(tie), row] > 7000
        # the model is data: the new term rebuilds from its string alone
        assert ExplicitModel.from_dict(tied.to_dict()).terms == tied.terms
    # the other rows are the restricted start's, and the new columns are zero there
    untied = _integrators_restricted(start, IdentConfig(), train)
    others = [j for j, s in enumerate(STATE_NAMES) if s not in ("ig_d", "ig_q")]
    assert np.array_equal(tied.coefficients[:len(terms), others], untied.coefficients[:, others])
    assert not tied.coefficients[len(terms):, others].any()
    # 1 % apart is beyond a tolerance of 0.5 %: nothing tied
    assert _integrators_restricted(start, IdentConfig.from_mapping({"filter_voltage_tie": 0.005}),
                                   train).terms == terms


def _fit_at_40_db(cfg, train, small):
    """A PISML fit of ``cfg`` on the training and small-signal records with 40 dB measurement noise."""
    from pisml_ros.plant.noise import add_measurement_noise

    return make_estimator("pisml", cfg).fit(add_measurement_noise(train, 40.0, seed=1),
                                            add_measurement_noise(small, 40.0, seed=2))


def test_physics_filter_fit_falls_back_to_free_filter_rows_where_its_refinement_is_lost(train, small, monkeypatch):
    # every restricted refinement breaks down here (as both did on vendor-c seed 0 at 40 dB): the
    # selection would take a start, so the starts are refined again with the filter rows free
    from pisml_ros.ident import estimators, selection
    from pisml_ros.ident.library import filter_row_mask

    real = estimators.refine_explicit
    restricted_starts = []

    def lost_when_restricted(model, *args, **kwargs):
        if model.metadata.get("filter_terms") == "physics":
            restricted_starts.append(model)
            return {}
        return real(model, *args, **kwargs)

    monkeypatch.setattr(estimators, "refine_explicit", lost_when_restricted)
    cfg = IdentConfig.from_mapping({**FAST, "filter_terms": "physics", "refine_rescue_ratio": "inf"})
    est = _fit_at_40_db(cfg, train, small)
    meta = est.explicit_model_.metadata
    record = meta["refinement_unrestricted"]
    assert restricted_starts and record["run"] and record["refinement_lost"]
    assert selection._refinement_family(record["selected_before"]) is None
    assert not any(name.startswith(("refined", "pruned")) for name in meta["selection"]["training_error_pct"]
                   if not name.endswith(" unrestricted"))
    assert record["ratio"] == pytest.approx(record["error_pct"] / meta["selection"]["noise_floor_pct"])
    # one family per start, scored and in the selection
    starts = [est.candidates_[name].metadata["refinement"]["start"]
              for name in ("refined unrestricted", "refined from noise-compensated backbone unrestricted")
              if name in est.candidates_]
    assert starts[0] in ("distilled", *[n for n in est.candidates_ if n.startswith("re-fit")])
    # (each start with its long-window branch's family, IdentConfig.refine_long_branch)
    suffixes = {" unrestricted", *[f" from {s} unrestricted" for s in starts[1:]]}
    assert {selection._refinement_family(name) for name in record["added"]} == \
        suffixes | {selection.LONG_BRANCH_SUFFIX + suffix for suffix in suffixes}
    assert set(record["added"]) <= set(meta["selection"]["training_error_pct"])
    assert est.metrics_["refinement_unrestricted"] == 1.0
    # the families' filter rows are free: the refined model keeps terms the physics mask rejects
    refined = est.candidates_["refined unrestricted"]
    signals = list(refined.state_names) + list(refined.input_names)
    mask = filter_row_mask(refined.terms, list(refined.state_names), signals, cfg.roles)
    assert np.any((refined.coefficients != 0) & ~mask)
    assert "filter_terms" not in refined.metadata or refined.metadata["filter_terms"] != "physics"
    # a restricted refinement that runs through the records but worse than holding their first
    # states (here: a constant drift) counts as lost too (stop 63, vendor-c seed 3: one prune round
    # at 1247 % with the hold at 33 %, and the backbone was chosen)
    def drifting_when_restricted(model, *args, **kwargs):
        if model.metadata.get("filter_terms") == "physics":
            coef = np.zeros_like(model.coefficients)
            coef[model.terms.index("1"), :] = 1e2
            return {"refined": ExplicitModel(model.state_names, model.input_names, model.terms, coef,
                                             {**model.metadata, "refinement": {}})}
        return real(model, *args, **kwargs)

    monkeypatch.setattr(estimators, "refine_explicit", drifting_when_restricted)
    drifted = _fit_at_40_db(cfg, train, small)
    scored = drifted.explicit_model_.metadata["selection"]["training_error_pct"]
    record = drifted.explicit_model_.metadata["refinement_unrestricted"]
    assert np.isfinite(scored["refined"]) and scored["refined"] > drifted.explicit_model_.metadata["selection"][
        "hold_error_pct"]
    assert record["run"] and record["refinement_lost"] and "refined unrestricted" in drifted.candidates_
    # where the restricted refinement gives the model and scores near the noise: no fallback
    monkeypatch.setattr(estimators, "refine_explicit", real)
    kept = make_estimator("pisml", IdentConfig.from_mapping({**FAST, "filter_terms": "physics"})).fit(train, small)
    record = kept.explicit_model_.metadata["refinement_unrestricted"]
    assert not record["run"] and not record["refinement_lost"]
    assert record["ratio"] is None  # clean records: no noise floor to compare with
    assert np.isfinite(kept.explicit_model_.metadata["selection"]["training_error_pct"]["refined"])
    assert not any(name.endswith(" unrestricted") for name in kept.candidates_)


def test_noisy_fit_whose_choice_is_inconsistent_with_the_rest_points_runs_the_rescue(train, small, monkeypatch):
    # stop 65, the scenarios' 5 kHz recording 0 at 40 dB: every candidate of the first refinement was
    # inconsistent with all 9 rest points, the chosen one scored 2.2x the noise floor (below the
    # rescue's ratio), and no second try ran. Here every candidate outside the rescue's family is
    # inconsistent with the rest points, at a ratio the rescue never reaches by itself
    from pisml_ros.ident import selection

    real = selection._inconsistent_points

    def inconsistent_but_the_rescue(name, candidates, points, *args, **kwargs):
        count = real(name, candidates, points, *args, **kwargs)
        return count if name.endswith(" with growing prior") else max(count, 1)

    monkeypatch.setattr(selection, "_inconsistent_points", inconsistent_but_the_rescue)
    cfg = IdentConfig.from_mapping({**FAST, "refine_rescue_ratio": 1e9, "refine_retry_ratio": 1e9,
                                    "filter_terms": "physics"})
    est = _fit_at_40_db(cfg, train, small)
    meta = est.explicit_model_.metadata
    rescue = meta["refinement_rescue"]
    assert rescue["ratio"] < cfg.refine_rescue_ratio and rescue["inconsistent_rest_points"] >= 1
    assert rescue["run"] and "refined with growing prior" in est.candidates_
    assert set(rescue["added"]) <= set(meta["selection"]["training_error_pct"])
    # the unrestricted fallback asks the same of the model the selection takes after the rescue
    fallback = meta["refinement_unrestricted"]
    assert fallback["ratio"] < cfg.refine_retry_ratio
    assert fallback["run"] == (fallback["inconsistent_rest_points"] > 0 or fallback["refinement_lost"])
    # consistent refined choices below the ratio: neither runs (the candidates from before the
    # refinement inconsistent, as those run the rescue whatever their score, tested below)
    monkeypatch.setattr(selection, "_inconsistent_points",
                        lambda name, *args, **kwargs: int(selection._refinement_family(name) is None))
    kept = _fit_at_40_db(cfg, train, small)
    meta = kept.explicit_model_.metadata
    assert not meta["refinement_rescue"]["run"] and meta["refinement_rescue"]["inconsistent_rest_points"] == 0
    assert not meta["refinement_unrestricted"]["run"] or meta["refinement_unrestricted"]["refinement_lost"]
    assert not any(name.endswith(" with growing prior") for name in kept.candidates_)


def test_noisy_fit_whose_choice_is_from_before_the_refinement_runs_the_rescue(train, small, monkeypatch):
    # stop 72, vendor-c seed 2 at 40 dB: every refined candidate ran away from the records' rest
    # points and the long-window prunes scored worse, so the selection took the trained backbone,
    # consistent and at 1.39x the noise floor (below the rescue's ratio): nothing tried again.
    # Here every refinement candidate outside the rescue's family is inconsistent with the rest
    # points and every other consistent, at a ratio the rescue never reaches by itself
    from pisml_ros.ident import selection

    real = selection._inconsistent_points

    def refinement_inconsistent(name, candidates, points, *args, **kwargs):
        if selection._refinement_family(name) is None or name.endswith(" with growing prior"):
            return 0
        return max(real(name, candidates, points, *args, **kwargs), 1)

    monkeypatch.setattr(selection, "_inconsistent_points", refinement_inconsistent)
    cfg = IdentConfig.from_mapping({**FAST, "refine_rescue_ratio": 1e9, "refine_retry_ratio": 1e9,
                                    "filter_terms": "physics"})
    est = _fit_at_40_db(cfg, train, small)
    meta = est.explicit_model_.metadata
    rescue = meta["refinement_rescue"]
    assert selection._refinement_family(rescue["selected_before"]) is None and rescue["before_refinement"]
    assert rescue["ratio"] < cfg.refine_rescue_ratio and rescue["inconsistent_rest_points"] == 0
    assert rescue["run"] and "refined with growing prior" in est.candidates_
    # the unrestricted fallback asks the same of the model the selection takes after the rescue
    fallback = meta["refinement_unrestricted"]
    assert fallback["before_refinement"] == (selection._refinement_family(fallback["selected_before"]) is None)
    assert fallback["run"] == (fallback["before_refinement"] or fallback["refinement_lost"])
    # on clean records a re-fit from before the refinement wins on its merits: no rescue there
    clean = make_estimator("pisml", cfg).fit(train, small)
    assert "refinement_rescue" not in clean.explicit_model_.metadata
    assert not clean.explicit_model_.metadata["refinement_unrestricted"]["run"] or \
        clean.explicit_model_.metadata["refinement_unrestricted"]["refinement_lost"]


def test_the_rescue_asks_for_less_than_the_further_tries():
    # stop 74: the rescue at 2.0x the noise floor (protocol recording 7 at 2.13x, 1.956 / 0.79 % IOD /
    # OOD without it, 0.278 / 0.667 % with it), the second start after it and the unrestricted
    # fallback at 2.5x (the clamp plant's recording 1 at 2.17x after its rescue: both ran, the same model)
    from pisml_ros.ident.selection import _noisy_choice_needs_retry

    cfg = IdentConfig()
    assert cfg.refine_rescue_ratio == 2.0 < cfg.refine_retry_ratio == 2.5
    chosen = "pruned +0.1 % x3 at long windows"
    assert _noisy_choice_needs_retry(chosen, 2.13, 0, cfg.refine_rescue_ratio)
    assert not _noisy_choice_needs_retry(chosen, 2.13, 0, cfg.refine_retry_ratio)
    assert not _noisy_choice_needs_retry(chosen, 1.79, 0, cfg.refine_rescue_ratio)
    # inconsistent with a rest point, or from before the refinement: whatever the ratio
    assert _noisy_choice_needs_retry(chosen, 1.0, 1, math.inf)
    assert _noisy_choice_needs_retry("trained backbone", 1.0, 0, math.inf)


def test_the_second_start_runs_where_the_first_starts_refinement_is_lost(train, small, monkeypatch):
    # stop 73, vendor-c recording 1 at 40 dB: both of the first start's refined models blew up, its
    # round 2 came out consistent near the floor but missed an LCL resonance; the second start runs
    from pisml_ros.ident import estimators
    from pisml_ros.ident.selection import LONG_BRANCH_SUFFIX, _unpruned_refinement_lost

    hold = 40.0
    assert _unpruned_refinement_lost({"refined": np.inf, "refined" + LONG_BRANCH_SUFFIX: 52.0}, hold)
    assert _unpruned_refinement_lost({"refined": np.nan, "pruned +0.1 %": 2.0}, hold)  # no long branch
    # one of the two runs through better than the hold: not lost, whatever its prune rounds score
    assert not _unpruned_refinement_lost({"refined": np.inf, "refined" + LONG_BRANCH_SUFFIX: 3.0}, hold)
    assert not _unpruned_refinement_lost({"refined": 2.5}, hold)
    # no refinement from that start at all: nothing to call lost (the selection decides)
    assert not _unpruned_refinement_lost({"pruned +0.1 %": 2.0}, hold)
    # the first start by its own models: another start's family does not count
    assert _unpruned_refinement_lost({"refined": np.inf, "refined from noise-compensated backbone": 2.0}, hold)
    # in a fit with the first start's family otherwise sufficient (refine_starts "fallback")
    monkeypatch.setattr(estimators, "_refinement_suffices", lambda *args, **kwargs: True)
    monkeypatch.setattr(estimators, "_unpruned_refinement_lost", lambda scores, hold: True)
    cfg = IdentConfig.from_mapping({**FAST, "refine_starts": "fallback", "refine_rescue_ratio": "inf"})
    est = _fit_at_40_db(cfg, train, small)
    second = est.explicit_model_.metadata["refinement_second_start"]
    assert second["run"] and second["first_lost"]
    assert f"refined from {second['start']}" in est.explicit_model_.metadata["selection"]["training_error_pct"]
    # (where it is not lost and the first family suffices, the second start is skipped: the rescue
    # test above, whose second start runs only after the rescue)


def test_centred_couplings_are_the_same_field_and_make_the_plain_signal_costly_to_drop(train):
    from pisml_ros.ident.estimators import _couplings_centred, frequency_centre
    from pisml_ros.ident.library import centred_terms, rebased
    from pisml_ros.plant.noise import add_measurement_noise

    clean, train = train, add_measurement_noise(train, 40.0, seed=1)

    signals = STATE_NAMES + INPUT_NAMES
    terms = ["1", "il_d", "ig_d", "Pf*il_d", "Pf*ig_q", "Pf**2", "Pf*Qf", "vc_d*ig_d + vc_q*ig_q", "Pf"]
    assert centred_terms(terms, signals, "Pf", 0.5) == [
        "1", "il_d", "ig_d", "il_d*(Pf - 0.5)", "ig_q*(Pf - 0.5)", "(Pf - 0.5)**2", "Qf*(Pf - 0.5)",
        "vc_d*ig_d + vc_q*ig_q", "Pf"]
    rng = np.random.default_rng(0)
    coef = rng.normal(size=(len(terms), len(STATE_NAMES))) * (rng.random((len(terms), len(STATE_NAMES))) < 0.5)
    start = ExplicitModel(STATE_NAMES, INPUT_NAMES, terms, coef)
    config = IdentConfig.from_mapping({"refine_centred_couplings": True})
    centred = _couplings_centred(start, config, train)
    centre = round(frequency_centre(train, "Pf"), 4)
    assert abs(centre - 0.5) < 0.05  # the droop power state sits at its set-point P* = 0.5 at rest
    assert centred.metadata["centred_couplings"] == {"signal": "Pf", "centre": centre}
    assert f"il_d*(Pf - {centre:g})" in centred.terms and "Pf*il_d" not in centred.terms
    # ig_q came in with its product: (Pf - P0)*ig_q needs it
    assert "ig_q" in centred.terms and "ig_q" not in terms
    x, u = np.concatenate([tr.x for tr in train]), np.concatenate([tr.u for tr in train])
    np.testing.assert_allclose(centred.vector_field(x, u), start.vector_field(x, u), rtol=1e-10, atol=1e-9)
    # off by default, and on clean records (there the equation-error re-fit separates them); a model
    # without products of the frequency state is returned as it is
    assert _couplings_centred(start, config, clean) is start
    assert _couplings_centred(start, IdentConfig(), train) is start
    plain = ExplicitModel(STATE_NAMES, INPUT_NAMES, ["1", "il_d"], np.ones((2, 13)))
    assert _couplings_centred(plain, config, train) is plain
    # terms that cannot express the field are refused
    with pytest.raises(ValueError, match="do not span"):
        rebased(["Pf*il_d"], np.ones((1, 1)), ["il_d*(Pf - 0.5)"], signals)
    # why: where Pf hardly leaves P0, Pf*il_d and il_d are nearly the same column, and dropping il_d
    # from a fit with both costs less than the noise does (the product takes its place); written
    # about P0 the product is only its deviation, and dropping il_d costs its whole effect
    pf = 0.5 + 0.001 * rng.standard_normal(400)
    il = rng.standard_normal(400)
    target = 377.0 * il + rng.standard_normal(400)
    rises = []
    for product in (pf * il, (pf - 0.5) * il):
        a = np.column_stack([il, product])
        full = np.linalg.lstsq(a, target, rcond=None)[0]
        cost = 0.5 * np.sum((a @ full - target) ** 2)
        rises.append(full[0] ** 2 / (2 * np.linalg.inv(a.T @ a)[0, 0]) / cost)  # dropping il_d, re-fitted
    assert rises[0] < 1.0 and rises[1] > 1e4


def test_a_fit_is_reproducible(train, small):
    """Same data, same seed: the same models (the network's initial weights come from the seed too)."""
    config = IdentConfig.from_mapping({**FAST, "refine": False})
    first = make_estimator("pisml", config).fit(train, small)
    import torch

    torch.rand(7)  # the global torch RNG moved on in between
    second = make_estimator("pisml", config).fit(train, small)
    np.testing.assert_array_equal(first.distilled_.coefficients, second.distilled_.coefficients)
    np.testing.assert_array_equal(first.explicit_model_.coefficients, second.explicit_model_.coefficients)


def _report_until_stopped(progress, stopped: list, steps: int | None = 100) -> None:
    """A job's progress reports every 0.05 s, ``steps`` of them (None: until one raises); the name
    of what a report raised goes to ``stopped``, and is raised again."""
    import itertools
    import time

    try:
        for _ in itertools.count() if steps is None else range(steps):
            time.sleep(0.05)
            progress(0.0, {})
    except Exception as err:
        stopped.append(type(err).__name__)
        raise


def test_refinements_run_side_by_side_report_from_the_caller_and_stop_together():
    import threading
    import time

    from pisml_ros.ident.estimators import _side_by_side

    caller = threading.current_thread()
    ran_in, reports = [], []

    def job(item, progress):
        ran_in.append(threading.current_thread())
        for step in range(1, 4):
            time.sleep(0.2)
            progress(step / 3, {f"loss_{item}": step})
        return item * 10

    def report(fraction, losses):
        assert threading.current_thread() is caller  # callbacks are called from the fitting thread only
        reports.append(fraction)

    assert _side_by_side(job, [1, 2], report, workers=2) == [10, 20]  # in the order of the items
    assert all(t is not caller for t in ran_in) and len(ran_in) == 2
    assert reports == sorted(reports) and reports[-1] == pytest.approx(1.0, abs=1e-9)
    # one after the other with one worker: the same results, progress still rising to 1
    reports.clear()
    assert _side_by_side(job, [1, 2], report, workers=1) == [10, 20]
    assert reports == sorted(reports) and reports[-1] == pytest.approx(1.0)

    # a job that fails stops the other at its next progress call, and its error is raised
    stopped = []

    def failing(item, progress):
        if item == "bad":
            time.sleep(0.3)
            raise FloatingPointError("window blew up")
        _report_until_stopped(progress, stopped)
        return "finished"

    started = time.monotonic()
    with pytest.raises(FloatingPointError, match="window blew up"):
        _side_by_side(failing, ["good", "bad"], lambda fraction, losses: None, workers=2)
    assert stopped == ["_StoppedBeside"] and time.monotonic() - started < 3.0

    # a cancellation raised by the report reaches the caller, and the jobs stop
    stopped.clear()

    def cancel(fraction, losses):
        raise IdentificationCancelled("cancelled during refinement")

    with pytest.raises(IdentificationCancelled):
        _side_by_side(failing, ["good", "good"], cancel, workers=2)
    assert stopped == ["_StoppedBeside", "_StoppedBeside"]


def test_a_job_started_beside_joins_the_side_by_side_run_and_stops_with_it():
    import threading
    import time

    import torch
    from threadpoolctl import threadpool_info

    from pisml_ros.ident.estimators import _Beside, _side_by_side

    def blas():
        return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]

    caller = threading.current_thread()
    seen: dict = {}

    def early(progress):
        seen["early"] = (threading.current_thread(), torch.get_num_threads(), blas())
        for step in range(1, 3):
            time.sleep(0.1)
            progress(step / 2, {"loss_early": step})
        return "early"

    def job(item, progress):
        seen[item] = (threading.current_thread(), torch.get_num_threads())
        time.sleep(0.3)
        progress(1.0, {f"loss_{item}": 1})
        return item * 10

    reports = []
    with torch_threads(2):
        before = blas()
        beside = _Beside(early)
        # the caller goes on with one thread while the job holds the other
        assert torch.get_num_threads() == 1
        beside.resume_caller()
        assert torch.get_num_threads() == 2
        out = _side_by_side(job, [1], lambda fraction, losses: reports.append((fraction, losses)), running=[beside])
        # its value after the items'; it ran on its own thread with one torch and one BLAS thread
        assert out == [10, "early"] and seen["early"][0] not in (caller, seen[1][0])
        assert seen["early"][1] == 1 and set(seen["early"][2]) <= {1} and seen[1][1] == 1
        assert [f for f, _ in reports] == sorted(f for f, _ in reports) and reports[-1][0] == pytest.approx(1.0)
        assert reports[-1][1] == {"loss_early": 2, "loss_1": 1}
        beside.close()  # (again: idempotent)
        # the caller's threads and the BLAS pools as they were
        assert torch.get_num_threads() == 2 and blas() == before

        # where the items end first, the caller waits for the job beside without spinning (a loop
        # holding the GIL would slow that job down)
        beside = _Beside(lambda progress: time.sleep(1.0) or "late")
        beside.resume_caller()
        spent = time.thread_time()
        assert _side_by_side(lambda item, progress: item, [3], lambda f, l: None, running=[beside]) == [3, "late"]
        assert time.thread_time() - spent < 0.3

        # a job beside that fails stops the items at their next progress call, and its error is raised
        def failing(progress):
            time.sleep(0.2)
            raise FloatingPointError("early window blew up")

        stopped = []

        def slow(item, progress):
            _report_until_stopped(progress, stopped)

        beside = _Beside(failing)
        beside.resume_caller()
        started = time.monotonic()
        with pytest.raises(FloatingPointError, match="early window blew up"):
            _side_by_side(slow, ["a"], lambda fraction, losses: None, running=[beside])
        assert stopped == ["_StoppedBeside"] and time.monotonic() - started < 3.0

        # a cancellation stops the job beside too, and close() restores what it changed
        stopped.clear()

        def endless(progress):
            _report_until_stopped(progress, stopped, steps=None)

        def cancel(fraction, losses):
            raise IdentificationCancelled("cancelled during refinement")

        beside = _Beside(endless)
        beside.resume_caller()
        with pytest.raises(IdentificationCancelled):
            _side_by_side(slow, ["a"], cancel, running=[beside])
        assert sorted(stopped) == ["_StoppedBeside", "_StoppedBeside"] and beside.done()
        # closed by the caller without a side-by-side run (the fit failed before it): stopped, restored
        stopped.clear()
        beside = _Beside(endless)
        beside.close()
        assert stopped == ["_StoppedBeside"] and torch.get_num_threads() == 2 and blas() == before


def test_side_by_side_runs_after_on_the_first_thread_a_job_leaves():
    import threading
    import time

    from pisml_ros.ident.estimators import _Deferred, _side_by_side

    caller = threading.current_thread()
    ended = {}

    def job(item, progress):
        time.sleep(item)
        progress(1.0, {})
        ended[item] = time.monotonic()
        return item

    def after():
        ended["after_thread"] = threading.current_thread()
        ended["after_start"] = time.monotonic()
        time.sleep(0.2)
        ended["after_end"] = time.monotonic()

    assert _side_by_side(job, [0.1, 0.8], lambda fraction, losses: None, workers=2, after=after) == [0.1, 0.8]
    # it started when the short job ended, ran beside the long one, and had ended by the return
    assert ended["after_thread"] is not caller
    assert ended[0.1] <= ended["after_start"] and ended["after_end"] < ended[0.8]
    # one after the other: after the jobs, on the caller's thread
    ended.clear()
    assert _side_by_side(job, [0.1, 0.2], lambda fraction, losses: None, workers=1, after=after) == [0.1, 0.2]
    assert ended["after_thread"] is caller and ended["after_start"] >= ended[0.2]

    # a deferred computation runs once, where it is run or first asked for, and raises where asked
    calls = []
    deferred = _Deferred(lambda: calls.append(1) or len(calls))
    deferred.run()
    assert deferred.value() == 1 and deferred.value() == 1 and calls == [1]

    def breaks():
        raise np.linalg.LinAlgError("singular")

    failing = _Deferred(breaks)
    failing.run()  # kept, not raised on the thread that ran it
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        failing.value()

def test_rivals_are_the_eligible_candidates_near_the_best_score():
    from pisml_ros.ident.selection import rival_names

    scores = {"refined": 2.2, "pruned +0.1 %": 3.2, "pruned +0.1 % x2": 3.5, "backbone": 2.0, "distilled": np.inf}
    eligible = ["refined", "pruned +0.1 %", "pruned +0.1 % x2", "distilled"]  # the backbone is not eligible
    assert rival_names("pruned +0.1 %", eligible, scores, 0.5) == ["refined"]
    assert rival_names("refined", eligible, scores, 0.5) == ["pruned +0.1 %"]
    assert rival_names("refined", eligible, scores, 0.7) == ["pruned +0.1 %", "pruned +0.1 % x2"]
    assert rival_names("refined", eligible, scores, 0.7, limit=1) == ["pruned +0.1 %"]
    assert rival_names("distilled", ["distilled"], scores, 0.5) == []


def test_window_costs_tell_a_lost_resonance_from_the_records_short_spans():
    """``trajfit.window_costs``: over 1 ms windows, starts fitted, the true damped resonance follows
    noisy step responses far better than one with the same gain and a resonance damped away (the
    rescue family's failure at 30 dB, stop 94); ``selection.window_misfits`` takes out the second."""
    from pisml_ros.ident.selection import SELECTION_WINDOW, window_misfits
    from pisml_ros.ident.trajfit import window_costs

    omega, dt = 9000.0, 1e-4

    def model(zeta):
        coef = np.array([[0.0, -omega ** 2], [1.0, -2 * zeta * omega], [0.0, omega ** 2]])
        return ExplicitModel(("x1", "x2"), ("u",), ["x1", "x2", "u"], coef, {})

    truth = model(0.07)
    rng = np.random.default_rng(0)
    records = []
    for k, level in enumerate((0.5, -0.8, 1.0)):
        t = np.arange(400) * dt
        u = np.where(t >= 0.01, level, 0.0)[:, None]
        x = np.zeros((t.size, 2))
        for i in range(t.size - 1):  # fine RK4 of the truth, the input held over each sample
            state, h = x[i].copy(), dt / 20
            for _ in range(20):
                f = lambda s: truth.vector_field(s, u[i])  # noqa: E731
                a = f(state)
                b = f(state + h / 2 * a)
                c = f(state + h / 2 * b)
                d = f(state + h * c)
                state = state + h / 6 * (a + 2 * b + 2 * c + d)
            x[i + 1] = state
        noise = 0.02 * np.array([1.0, omega]) * rng.standard_normal(x.shape)
        records.append(Trajectory(k, t, x + noise, u))
    data = Dataset(("x1", "x2"), ("u",), records, {"dt": dt})
    costs = window_costs({"truth": truth, "damped": model(1.5), "again": model(0.07)}, data, SELECTION_WINDOW)
    assert costs["truth"] == pytest.approx(costs["again"])
    assert 2 * (SELECTION_WINDOW + 1) * (costs["damped"] - costs["truth"]) > 1000
    assert window_misfits(["truth", "damped"], costs, 300.0) == ["damped"]
    assert window_misfits(["truth", "damped"], costs, np.inf) == []  # off
    assert window_misfits(["truth", "damped"], {}, 300.0) == []  # no costs: nothing to judge


def test_selection_passes_over_a_family_the_short_windows_reject_on_low_snr_records(train):
    """``selection_window_excess``: a family that scores best run freely but whose short-window cost is
    far above another's does not compete; within the excess, or without costs, the scores decide.
    Which records are low-SNR (``low_snr_below_db``), and the growing windows their second
    refinement pass takes (``refine_growing_windows_low_snr``)."""
    from pisml_ros.ident.estimators import LOW_SNR_SUFFIX, low_snr, refinement_passes
    from pisml_ros.ident.selection import _configured_selection, _selected
    from pisml_ros.plant.noise import add_measurement_noise

    def model(nonzero):
        coef = np.zeros((6, 1))
        coef[:nonzero] = 1.0
        return ExplicitModel(("x",), ("u",), ["1", "x", "u", "x**2", "x*u", "u**2"], coef, {})

    candidates = {"refined": model(6), "pruned +0.1 %": model(5),
                  "refined with growing prior": model(6), "pruned +0.1 % with growing prior": model(4)}
    scores = {"refined": 9.0, "pruned +0.1 %": 8.0, "refined with growing prior": 5.0,
              "pruned +0.1 % with growing prior": 5.1}
    costs = {"refined": 2829.0, "pruned +0.1 %": 2829.1, "refined with growing prior": 2926.0,
             "pruned +0.1 % with growing prior": 2892.0}

    def chosen(**kwargs):
        return _selected(candidates["refined"], candidates, scores, tolerance=0.5, **kwargs).metadata["selection"]

    assert chosen()["chosen"] == "pruned +0.1 % with growing prior"
    judged = chosen(window_costs=costs, window_excess=300.0)
    assert judged["chosen"] == "pruned +0.1 %"
    assert judged["window_rejected"] == ["refined with growing prior", "pruned +0.1 % with growing prior"]
    assert judged["window_costs"] == costs and judged["window_excess"] == 300.0
    # 22 x 62.9 = 1384 for the pruned one: within an excess of 1500 it competes, and wins again
    assert chosen(window_costs=costs, window_excess=1500.0)["chosen"] == "pruned +0.1 % with growing prior"
    assert chosen(window_costs=costs)["chosen"] == "pruned +0.1 % with growing prior"  # excess inf: off
    cfg = IdentConfig()
    assert cfg.selection_window_excess == 300.0 and cfg.refine_growing_windows_low_snr == (5, 10, 25, 50)
    configured = _configured_selection(candidates["refined"], candidates, scores, cfg, {}, np.inf, window_costs=costs)
    assert configured.metadata["selection"]["chosen"] == "pruned +0.1 %"
    # which records are low-SNR: the protocol's at 30 and 35 dB, not at 40 dB nor clean ones
    at30, at40 = add_measurement_noise(train, 30.0, seed=1), add_measurement_noise(train, 40.0, seed=1)
    assert cfg.low_snr_below_db == 37.5 and low_snr(add_measurement_noise(train, 35.0, seed=1), cfg)
    assert low_snr(at30, cfg) and not low_snr(at40, cfg) and not low_snr(train, cfg)
    always, never = (IdentConfig.from_mapping({"low_snr_below_db": v}) for v in ("inf", 0))
    assert low_snr(at40, always) and not low_snr(train, always) and not low_snr(at30, never)
    def stages(config):  # each pass's growing stages on the 30 dB records, (window, evaluations), and window counts
        return [(list(zip(c.refine_growing_windows, c.refine_growing_evaluations)), c.refine_growing_max_windows)
                for c, _ in refinement_passes(at30, config)]

    default = ([(10, 30), (25, 20), (50, 20)], ())
    assert stages(cfg) == [default, ([(5, 20), (10, 30), (25, 20), (50, 20)], ())]
    assert [suffix for _, suffix in refinement_passes(at30, cfg)] == ["", LOW_SNR_SUFFIX]
    assert refinement_passes(at40, cfg) == [(cfg, "")] and refinement_passes(train, cfg) == [(cfg, "")]
    longer = IdentConfig.from_mapping({"refine_growing_windows_low_snr": "20,50,100",
                                       "refine_growing_evaluations_low_snr": "", "refine_growing_max_windows": "0,9,0"})
    # (the default stages' evaluations where the low-SNR ones are not given; their window counts default stages' only)
    assert stages(longer) == [(default[0], (0, 9, 0)), ([(20, 30), (50, 20), (100, 20)], ())]
    assert refinement_passes(at40, longer) == [(longer, "")]
    off = IdentConfig.from_mapping({"refine_growing_windows_low_snr": "", "refine_growing_evaluations_low_snr": ""})
    assert stages(off) == [default]
    for bad in ({"refine_growing_windows_low_snr": "20,50"},
                {"refine_growing_windows_low_snr": "20,50", "refine_growing_evaluations_low_snr": "5,5,5"},
                {"refine_growing_windows_low_snr": "", "refine_growing_evaluations_low_snr": "5"}):
        with pytest.raises(ConfigError, match="refine_growing_windows_low_snr"):
            IdentConfig.from_mapping(bad)
    with pytest.raises(ConfigError, match="selection_window_excess"):
        IdentConfig.from_mapping({"selection_window_excess": -1})
    for bad in (-1, "nan"):
        with pytest.raises(ConfigError, match="low_snr_below_db must be an SNR in dB"):
            IdentConfig.from_mapping({"low_snr_below_db": bad})


@pytest.mark.slow
def test_low_snr_records_are_refined_again_in_their_own_growing_windows_and_both_passes_compete(train, small):
    """On low-SNR records (30 dB here) the refinement runs twice: in the default growing windows and in
    ``refine_growing_windows_low_snr``; the second pass's candidates, renamed with LOW_SNR_SUFFIX,
    compete in the selection, its records sit under ``low_snr_pass``, and the estimator's configuration
    is left as it was given."""
    from pisml_ros.ident.estimators import LOW_SNR_SUFFIX
    from pisml_ros.ident.selection import _refinement_family
    from pisml_ros.plant.noise import add_measurement_noise

    cfg = IdentConfig.from_mapping({**FAST, "refine_growing_windows_low_snr": "5,10",
                                    "refine_growing_evaluations_low_snr": "2,2", "limiter_search": False})
    est, updates = make_estimator("pisml", cfg), []
    est.fit(add_measurement_noise(train, 30.0, seed=1), add_measurement_noise(small, 30.0, seed=2),
            callback=updates.append)
    # the two passes share the refinement's part of the progress: it never goes back
    progress = [u.progress for u in updates]
    assert progress == sorted(progress) and progress[-1] == 1.0
    assert est.config is cfg and cfg.refine_growing_windows_low_snr == (5, 10)
    second = sorted(name for name in est.candidates_ if name.endswith(LOW_SNR_SUFFIX))
    first = sorted(name for name in est.candidates_ if name.startswith(("refined", "pruned"))
                   and not name.endswith(LOW_SNR_SUFFIX))
    assert "refined" + LOW_SNR_SUFFIX in second and "refined" in first
    windows = {name: est.candidates_[name].metadata["refinement"].get("growing_windows", {}).get("windows")
               for name in first + second if name.startswith("refined")}
    assert windows["refined"] == [10, 25, 50] and windows["refined" + LOW_SNR_SUFFIX] == [5, 10]
    # one family each: a pruned model of the second pass is judged against that pass's refined model
    assert _refinement_family("pruned +0.1 %" + LOW_SNR_SUFFIX) == LOW_SNR_SUFFIX
    meta = est.explicit_model_.metadata
    assert meta["low_snr_pass"]["windows"] == [5, 10] and meta["low_snr_pass"]["suffix"] == LOW_SNR_SUFFIX
    assert "refinement_starts" in meta["low_snr_pass"] and "refinement_starts" in meta
    assert json.loads(est.explicit_model_.to_json())["metadata"]["low_snr_pass"]["windows"] == [5, 10]
    # both passes' candidates were scored and judged by the short windows (low-SNR records)
    selection = meta["selection"]
    assert set(second) <= set(selection["training_error_pct"])
    assert est.metrics_["refinement_passes"] == 2.0
    assert meta["training"]["estimated_snr_db"] == pytest.approx(30.0, abs=0.5)
    # pisml identify's summary says what the engine made of the noise
    from pisml_ros.ident.noise import noise_note
    line = noise_note(est.explicit_model_)
    assert line.startswith(f"records' estimated SNR {meta['training']['estimated_snr_db']:.1f} dB (the noise alone")
    assert line.endswith(f'a second refinement pass in windows of 5, 10 samples (candidates "...{LOW_SNR_SUFFIX}")')
    # 40 dB records: one pass
    once = make_estimator("pisml", cfg).fit(add_measurement_noise(train, 40.0, seed=1),
                                            add_measurement_noise(small, 40.0, seed=2))
    assert not any(name.endswith(LOW_SNR_SUFFIX) for name in once.candidates_)
    assert "low_snr_pass" not in once.explicit_model_.metadata and once.metrics_["refinement_passes"] == 1.0
    note = noise_note(once.explicit_model_)
    assert "estimated SNR" in note and "refinement pass" not in note


@pytest.mark.slow
def test_a_second_neural_residual_is_refined_from_its_own_start_and_its_families_compete(train, small):
    """``residual_fits`` 2 on noisy records: the residual is trained again from the next seed, distilled,
    re-fitted and refined from its own start; its families, renamed `` (residual 2)``, compete in the
    selection beside the first fit's (one family each), its record sits under ``residual_fits``, the
    progress never goes back and the fit's own metrics stay the first pass's. Clean records: one fit."""
    from pisml_ros.ident.selection import _refinement_family
    from pisml_ros.plant.noise import add_measurement_noise

    cfg = IdentConfig.from_mapping({**FAST, "residual_fits": 2, "limiter_search": False})
    assert IdentConfig().residual_fits == 2 and cfg.seed == 0
    est, updates = make_estimator("pisml", cfg), []
    noisy_train, noisy_small = add_measurement_noise(train, 40.0, seed=1), add_measurement_noise(small, 40.0, seed=2)
    est.fit(noisy_train, noisy_small, callback=updates.append)
    progress = [u.progress for u in updates]
    assert progress == sorted(progress) and progress[-1] == 1.0
    assert any(u.stage == "training (residual 2)" for u in updates)
    suffix = " (residual 2)"
    second = sorted(name for name in est.candidates_ if name.endswith(suffix))
    assert "refined" + suffix in second and "refined" in est.candidates_
    # its own residual, its own refinement: not the first fit's models under another name
    assert not np.allclose(est.candidates_["refined" + suffix].coefficients, est.candidates_["refined"].coefficients)
    assert _refinement_family("pruned +0.1 % x3 at long windows" + suffix) == " at long windows" + suffix
    # what came before the refinement stays the first fit's alone
    assert "distilled" + suffix not in est.candidates_ and "distilled" in est.candidates_
    meta = est.explicit_model_.metadata
    [record] = meta["residual_fits"]
    assert record["seed"] == 1 and record["suffix"] == suffix and record["seconds"] > 0
    assert record["refinement_starts"] and "refinement_starts" in meta
    assert set(second) <= set(meta["selection"]["training_error_pct"])
    assert json.loads(est.explicit_model_.to_json())["metadata"]["residual_fits"][0]["seed"] == 1
    assert est.metrics_["refinement_passes"] == 1.0 and est.metrics_["residual_fit_seconds"] > 0
    assert "training (residual 2)" in est.history_ and "training" in est.history_
    assert est.config is cfg and cfg.seed == 0
    from pisml_ros.ident.noise import noise_note
    assert noise_note(est.explicit_model_).endswith(
        '; 2 neural residuals, each refined from its own start (candidates "... (residual 2)")')
    # clean records: the first fit alone
    clean = make_estimator("pisml", cfg).fit(train, small)
    assert not any(name.endswith(suffix) for name in clean.candidates_)
    assert "residual_fits" not in clean.explicit_model_.metadata
