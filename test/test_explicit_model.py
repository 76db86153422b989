"""ExplicitModel: the JSON contract, safe loading, evaluation against the plant it was fitted to."""
import json

import numpy as np
import pytest

from pisml_ros.ident.library import extended_library, monomial_basis, physics_library
from pisml_ros.ident.roles import SignalRoles
from pisml_ros.model import ExplicitModel, ModelFormatError
from pisml_ros.plant import InverterPlant
from pisml_ros.plant.scenarios import generate, schedules_for
from pisml_ros.signals import INPUT_NAMES, STATE_NAMES


@pytest.fixture(scope="module")
def truth():
    """The plant written exactly in the monomial basis of Θ ∪ Θ_ext (least squares on its vector field)."""
    plant = InverterPlant()
    roles = SignalRoles()
    basis, _ = monomial_basis(physics_library(roles, STATE_NAMES) + extended_library(roles, STATE_NAMES),
                              STATE_NAMES + INPUT_NAMES)
    schedules, duration = schedules_for("train", seed=0)
    data = generate(plant, schedules, duration)
    x = np.concatenate([tr.x for tr in data])
    u = np.concatenate([tr.u for tr in data])
    model = ExplicitModel(STATE_NAMES, INPUT_NAMES, basis, np.zeros((len(basis), 13)))
    theta = model.features(x, u)
    coef = np.linalg.lstsq(theta, plant.vector_field(x, u), rcond=None)[0]
    coef[np.abs(coef) < 1e-7] = 0.0
    ref = [{"inputs": [1.0, 0.0], "state": plant.equilibrium(1.0).tolist()}]
    return ExplicitModel(STATE_NAMES, INPUT_NAMES, basis, coef, {"reference_points": ref}), plant


def test_true_model_in_the_monomial_basis(truth):
    model, plant = truth
    assert model.n_parameters == 88  # the "about 88" monomial coefficients
    rng = np.random.default_rng(0)
    x = plant.equilibrium(0.9) + 0.05 * rng.standard_normal(13)
    assert np.allclose(model.vector_field(x, [0.85, 0.1]), plant.vector_field(x, [0.85, 0.1]), rtol=1e-6, atol=1e-5)
    assert np.allclose(model.jacobian(x, [0.85, 0.1]), plant.jacobian(x, [0.85, 0.1]), rtol=1e-6, atol=1e-4)


def test_equilibrium_eigenvalues_and_simulation_match_the_plant(truth):
    model, plant = truth
    for ug in (0.4, 0.8, 1.2):
        assert np.allclose(np.sort_complex(model.eigenvalues(ug, 0.0)), np.sort_complex(plant.eigenvalues(ug)),
                           rtol=1e-5, atol=1e-4)
    schedules, duration = schedules_for("test")
    data = generate(plant, schedules, duration)
    pred = model.simulate(data)
    for a, b in zip(pred, data):
        assert np.linalg.norm(a.x - b.x) / np.linalg.norm(b.x) < 1e-6


def test_json_round_trip_and_rebuild_without_the_package(tmp_path, truth):
    model, _ = truth
    path = model.save(tmp_path / "m.json")
    data = json.loads(path.read_text())
    assert data["format"] == "pisml-explicit-model/1"
    assert np.array(data["coefficients"]).shape == (len(data["terms"]), len(data["states"]))
    again = ExplicitModel.load(path)
    assert np.array_equal(again.coefficients, model.coefficients) and again.terms == model.terms
    # rebuild f(x, u) with plain sympy from the JSON alone
    import sympy

    names = data["states"] + data["inputs"]
    syms = sympy.symbols(names)
    terms = [sympy.sympify(t, locals=dict(zip(names, syms))) for t in data["terms"]]
    f = sympy.lambdify(syms, (sympy.Matrix([terms]) * sympy.Matrix(data["coefficients"])), "numpy")
    z = np.concatenate([model.metadata["reference_points"][0]["state"], [1.0, 0.0]])
    assert np.allclose(np.ravel(f(*z)), model.vector_field(z[:13], z[13:]), atol=1e-9)
    assert len(model.equations()) == 13 and model.latex()[0].startswith(r"\dot{\delta}")


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d.update(format="other"), "field format"),
    (lambda d: d.pop("terms"), "missing field 'terms'"),
    (lambda d: d.update(terms=["__import__('os').system('x')"] + d["terms"][1:]), "only calls of"),
    (lambda d: d.update(terms=["nope*delta"] + d["terms"][1:]), "unknown signal 'nope'"),
    (lambda d: d.update(coefficients=d["coefficients"][:-1]), "expected n_terms x n_states"),
    (lambda d: d["coefficients"][0].__setitem__(0, "x"), "numeric matrix"),
])
def test_bad_model_files_are_rejected(tmp_path, truth, mutate, message):
    data = truth[0].to_dict()
    data = json.loads(json.dumps(data))
    mutate(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ModelFormatError, match=message):
        ExplicitModel.load(path)


@pytest.mark.slow
def test_trajectory_refinement_recovers_perturbed_coefficients(truth):
    """The multiple-shooting refiner (issue 3 groundwork) pulls perturbed coefficients back onto the data."""
    from pisml_ros.ident.trajfit import TrajectoryFitter

    model, plant = truth
    data, start, weights = _perturbed_problem(model, plant, seed=2, duration=0.01, spread=0.02, rng_seed=1)
    fitter = TrajectoryFitter(model._terms, 13, data.dt, window=20, substeps=2, weights=weights)
    result = fitter.fit(start, model.coefficients != 0, data, lambda_jac=0.0, max_nfev=6)
    assert _replay_error(model, result.coefficients, data) < 0.1 * _replay_error(model, start, data)


def _perturbed_problem(model, plant, seed, duration, spread, rng_seed):
    """Two clean training records, the true coefficients perturbed by ``spread``, and residual weights."""
    schedules, _ = schedules_for("train", seed=seed, n_traj=2)
    data = generate(plant, schedules, duration)
    rng = np.random.default_rng(rng_seed)
    start = model.coefficients * (1 + spread * rng.standard_normal(model.coefficients.shape))
    rms = np.sqrt(np.mean(np.concatenate([tr.x for tr in data]) ** 2, axis=0))
    return data, start, 1 / (1e-4 * rms)


def _replay_error(model, coef, data):
    """Worst relative error of the model with ``coef`` replaying ``data`` from its first samples."""
    pred = ExplicitModel(STATE_NAMES, INPUT_NAMES, model.terms, coef).simulate(data)
    return max(np.linalg.norm(a.x - b.x) / np.linalg.norm(b.x) for a, b in zip(pred, data))


@pytest.mark.slow
def test_refinement_exact_and_iterative_steps_agree(truth):
    """The dense exact trust-region step (the default at the benchmark's sizes) and LSMR reach the same fit."""
    from pisml_ros.ident.trajfit import TrajectoryFitter

    model, plant = truth
    data, start, weights = _perturbed_problem(model, plant, seed=4, duration=0.006, spread=0.01, rng_seed=2)
    mask = model.coefficients != 0
    results = {}
    for name, sizes in (("exact", (0, TrajectoryFitter.exact_range[1])), ("lsmr", (0, 0))):
        fitter = TrajectoryFitter(model._terms, 13, data.dt, window=10, substeps=2, weights=weights)
        fitter.exact_range = sizes
        results[name] = fitter.fit(start, mask, data, lambda_jac=0.0, max_nfev=4)
    exact = _replay_error(model, results["exact"].coefficients, data)
    assert exact < 0.2 * _replay_error(model, start, data)
    assert exact < 2 * _replay_error(model, results["lsmr"].coefficients, data) + 1e-9


def test_refinement_stops_when_told_the_fit_is_not_improving(truth):
    """``keep_going`` is asked at every accepted point after the start; False ends the fit there,
    with what it had."""
    from pisml_ros.ident.trajfit import TrajectoryFitter

    model, plant = truth
    data, start, weights = _perturbed_problem(model, plant, seed=4, duration=0.004, spread=0.01, rng_seed=2)
    fitter = TrajectoryFitter(model._terms, 13, data.dt, window=10, substeps=2, weights=weights)
    asked = []

    def keep_going(coef):
        asked.append(coef.copy())
        return False

    result = fitter.fit(start, model.coefficients != 0, data, lambda_jac=0.0, max_nfev=6, keep_going=keep_going)
    assert result.abandoned and len(asked) == 1 and result.nfev < 6
    np.testing.assert_array_equal(result.coefficients, asked[0])
    assert np.all(np.isfinite(result.coefficients)) and np.all((result.coefficients != 0) <= (start != 0))


def test_a_refinement_goes_on_while_its_free_run_error_falls():
    from pisml_ros.ident.estimators import _worth_continuing

    def stops_at(errors, start):
        return next((k + 1 for k in range(len(errors)) if not _worth_continuing(errors[:k + 1], start)), None)

    # the measured sequences (benchmark recordings): at 40 dB never better than the start, and not
    # falling -> stopped at the 3rd point; at 60 dB worse at first but falling, then better -> on
    assert stops_at([5.57, 5.41, 5.63, 6.01, 5.48], 4.39) == 3
    assert stops_at([2.93, 2.14, 1.81, 1.32, 1.35, 1.27], 1.66) is None
    # a diverged check (inf) stops it; one better than the start never does
    assert stops_at([2.0, float("inf")], 1.5) == 2
    assert stops_at([1.0, 1.2, 1.3], 1.5) is None
