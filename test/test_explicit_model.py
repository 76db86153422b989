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
    assert 0 < result.accepted < result.nfev == 6  # the start's evaluation is no step
    # a heavy damping to start from: the same budget hardly moves the coefficients
    damped = fitter.fit(start, model.coefficients != 0, data, lambda_jac=0.0, max_nfev=6, damping=1e6)
    assert _replay_error(model, damped.coefficients, data) > 0.5 * _replay_error(model, start, data)
    # the same problem gives the same coefficients, bit for bit (torch's CPU lstsq in the step did not:
    # a different solution on every call for the same matrix)
    again = fitter.fit(start, model.coefficients != 0, data, lambda_jac=0.0, max_nfev=6)
    np.testing.assert_array_equal(again.coefficients, result.coefficients)


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


def _plain_shooting(problem, terms, theta, z, inputs=None):
    """A shooting problem's trajectory residuals written plainly, (windows, samples·states), and their
    Jacobians in θ and in each window's start offset z by torch's autodiff. ``inputs(k, theta)``: the
    windows' inputs at sample k (default: as held, ``problem.U[:, k]``)."""
    import torch

    inputs = inputs or (lambda k, theta: problem.U[:, k])

    def residuals(theta, z):
        c = problem._matrix(theta)
        x = problem.X[:, 0] + z * problem.x_unit
        out = [(x - problem.X[:, 0]) * problem.res_weight]
        for k in range(problem.window):
            u = inputs(k, theta)
            for _ in range(problem.substeps):
                f = lambda y: terms.evaluate_torch(torch.cat([y, u], -1)) @ c  # noqa: E731
                k1 = f(x)
                k2 = f(x + 0.5 * problem.h * k1)
                k3 = f(x + 0.5 * problem.h * k2)
                k4 = f(x + problem.h * k3)
                x = x + problem.h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            out.append((x - problem.X[:, k + 1]) * problem.res_weight)
        return torch.stack(out, 1).reshape(problem.n_windows, -1)

    jc = torch.func.jacfwd(residuals, argnums=0)(theta, z)
    jz_all = torch.func.jacfwd(residuals, argnums=1)(theta, z)
    jz = torch.stack([jz_all[w, :, w, :] for w in range(problem.n_windows)])
    return residuals(theta, z), jc, jz


@pytest.mark.parametrize("threads, single", [(1, False), (2, False), (2, True)])
def test_shooting_normal_equations_match_autodiff(truth, threads, single):
    """The forward sensitivities integrated beside the states give the same Gauss-Newton blocks
    as torch's autodiff of the residuals, and the profiled Hessian is the Schur complement of the
    window start states in the dense JᵀJ; the same with the windows shared out over two threads,
    and to float32's precision with the coefficient tangents in float32."""
    import torch

    from pisml_ros.ident.trajfit import TrajectoryFitter, _ShootingProblem

    model, plant = truth
    data, start, weights = _perturbed_problem(model, plant, seed=4, duration=0.002, spread=0.01, rng_seed=2)
    small = generate(plant, *schedules_for("smallsignal", n_traj=1, duration=0.008))
    fitter = TrajectoryFitter(model._terms, 13, data.dt, window=4, substeps=2, weights=weights, threads=threads,
                              single_precision=single)
    problem = _ShootingProblem(fitter, start, model.coefficients != 0, data, small, lambda_jac=1.0, ss_stride=5)
    assert problem.n_windows >= 2 * threads
    theta = torch.tensor(start.ravel()[problem.idx] / problem.scale)
    z = 0.1 * torch.randn((problem.n_windows, 13), generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    n_win = problem.n_windows
    r, jc, jz = _plain_shooting(problem, model._terms, theta, z)
    js = torch.func.jacfwd(problem._smallsignal_residuals)(theta)
    rs = problem._smallsignal_residuals(theta)
    blocks = problem.normal_equations(theta, z)
    expected = {"H": torch.einsum("wrc,wrd->cd", jc, jc) + js.T @ js, "g": torch.einsum("wrc,wr->c", jc, r) + js.T @ rs,
                "A": jz.transpose(1, 2) @ jz, "E": jz.transpose(1, 2) @ jc, "bz": torch.einsum("wrk,wr->wk", jz, r)}
    if single:
        for name, value in expected.items():
            assert blocks[name].dtype == torch.float64
            close = 1e-5 if name in ("H", "g", "E") else 1e-9  # the start states' blocks stay float64
            np.testing.assert_allclose(blocks[name].numpy(), value.numpy(), rtol=close,
                                       atol=close * float(value.abs().max()))
        # float32, not float64 relabelled
        assert not np.allclose(blocks["E"].numpy(), expected["E"].numpy(), rtol=1e-9,
                               atol=1e-9 * float(expected["E"].abs().max()))
        problem.close()
        return
    for name, value in expected.items():
        np.testing.assert_allclose(blocks[name].numpy(), value.numpy(), rtol=1e-9, atol=1e-9 * float(value.abs().max()))
    # the start states' blocks alone (fit_starts' pass, shared out too)
    starts_only = problem._shoot(theta, z, "z")[1]
    assert set(starts_only) == {"A", "bz"}
    for name in ("A", "bz"):
        np.testing.assert_allclose(starts_only[name].numpy(), expected[name].numpy(), rtol=1e-9,
                                   atol=1e-9 * float(expected[name].abs().max()))
    assert problem.cost(theta, z) == pytest.approx(0.5 * float((r ** 2).sum() + (rs ** 2).sum()), rel=1e-12)
    # a cost pass keeps its states, and the normal equations at its point start from them ...
    kept = problem.normal_equations(theta, z)
    for name in expected:
        np.testing.assert_allclose(kept[name].numpy(), blocks[name].numpy(), rtol=1e-12, atol=1e-12 * float(blocks[name].abs().max()))
    problem._kept[3][:] = [2 * value for value in problem._kept[3]]  # (its residuals: seen in the gradient)
    assert not torch.allclose(problem.normal_equations(theta, z)["g"], blocks["g"])
    # ... only there
    problem.cost(theta, z + 0.01)
    np.testing.assert_allclose(problem.normal_equations(theta, z)["g"].numpy(), blocks["g"].numpy(), rtol=1e-12)
    # the profiled Hessian: the Schur complement of the start states in the dense JᵀJ
    dense = torch.cat([torch.cat([jc.reshape(-1, jc.shape[-1]), torch.block_diag(*jz)], dim=1),
                       torch.cat([js, torch.zeros((js.shape[0], 13 * n_win))], dim=1)]).numpy()
    n_c = problem.idx.size
    h = dense.T @ dense
    schur = h[:n_c, :n_c] - h[:n_c, n_c:] @ np.linalg.solve(h[n_c:, n_c:], h[n_c:, :n_c])
    expected_h = schur / np.outer(problem.scale, problem.scale)
    np.testing.assert_allclose(problem.profiled_hessian(blocks), expected_h, rtol=1e-6,
                               atol=1e-9 * np.abs(expected_h).max())
    problem.close()


@pytest.mark.parametrize("threads", [1, 2])
def test_held_training_levels_errors_are_parameters_with_their_prior(truth, threads):
    """With the training records' inputs held at their stretch means (noisy measured inputs), each
    held level's error is a parameter after the coefficients, shared by every window on it, with the
    prior N(0, σ²/n): the Gauss-Newton blocks match torch's autodiff of the residuals with the held
    levels moved by them and the prior's rows appended; the profiled Hessian minimises them out."""
    import torch

    from pisml_ros.data import Dataset
    from pisml_ros.ident.trajfit import TrajectoryFitter, _ShootingProblem, held_level_counts, held_window_levels

    model, plant = truth
    data, start, weights = _perturbed_problem(model, plant, seed=4, duration=0.002, spread=0.01, rng_seed=2)
    sigma = {"ug": 0.01, "theta_g": 0.02}
    data = Dataset(data.state_names, data.input_names, list(data), {**data.metadata, "inputs_denoised": sigma})
    fitter = TrajectoryFitter(model._terms, 13, data.dt, window=4, substeps=2, weights=weights, threads=threads,
                              held_levels=True)
    problem = _ShootingProblem(fitter, start, model.coefficients != 0, data, None, lambda_jac=0.0, ss_stride=5)
    counts = held_level_counts(list(data), np.array([0.01, 0.02]))
    levels = sorted((j, v) for j in range(2) for v, k in counts[j].items() if k >= 8)
    assert problem.n_levels == len(levels) >= 3 and problem.n_params == problem.n_c + problem.n_levels
    n_c = problem.n_c
    table = problem.level_table  # (windows, samples, inputs, levels): ∂u/∂θ_level
    theta = torch.tensor(np.concatenate([start.ravel()[problem.idx] / problem.scale,
                                         np.linspace(-1.0, 1.0, problem.n_levels)]))
    z = 0.1 * torch.randn((problem.n_windows, 13), generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    n_win = problem.n_windows
    r, jc, jz = _plain_shooting(problem, model._terms, theta, z,
                                inputs=lambda k, theta: problem.U[:, k] + table[:, k] @ theta[n_c:])
    assert float(jc[..., n_c:].abs().max()) > 0  # the levels move the states
    prior = torch.cat([torch.zeros(n_c), torch.ones(problem.n_levels)])
    blocks = problem.normal_equations(theta, z)
    expected = {"H": torch.einsum("wrc,wrd->cd", jc, jc) + torch.diag(prior),
                "g": torch.einsum("wrc,wr->c", jc, r) + prior * theta,
                "A": jz.transpose(1, 2) @ jz, "E": jz.transpose(1, 2) @ jc, "bz": torch.einsum("wrk,wr->wk", jz, r)}
    for name, value in expected.items():
        np.testing.assert_allclose(blocks[name].numpy(), value.numpy(), rtol=1e-9, atol=1e-9 * float(value.abs().max()))
    assert problem.cost(theta, z) == pytest.approx(0.5 * float((r ** 2).sum() + (theta[n_c:] ** 2).sum()), rel=1e-12)
    # the profiled Hessian: the start states and the levels minimised out of the dense JᵀJ
    dense = torch.cat([torch.cat([jc.reshape(-1, jc.shape[-1]), torch.block_diag(*jz)], dim=1),
                       torch.cat([torch.diag(prior)[n_c:], torch.zeros((problem.n_levels, 13 * n_win))], dim=1)])
    h = (dense.T @ dense).numpy()
    schur = h[:n_c, :n_c] - h[:n_c, n_c:] @ np.linalg.solve(h[n_c:, n_c:], h[n_c:, :n_c])
    expected_h = schur / np.outer(problem.scale, problem.scale)
    np.testing.assert_allclose(problem.profiled_hessian(blocks), expected_h, rtol=1e-6,
                               atol=1e-9 * np.abs(expected_h).max())
    assert problem.coefficients(theta.numpy()).shape == start.shape
    problem.close()
    # inputs taken as exact (no inputs_denoised), or the option off: no level parameters
    exact = Dataset(data.state_names, data.input_names, list(data),
                    {k: v for k, v in data.metadata.items() if k != "inputs_denoised"})
    assert _ShootingProblem(fitter, start, model.coefficients != 0, exact, None, 0.0, 5).n_levels == 0
    fitter.held_levels = False
    assert _ShootingProblem(fitter, start, model.coefficients != 0, data, None, 0.0, 5).n_levels == 0
    # held_window_levels: one level per input and value with enough samples (σ/√n), -1 elsewhere
    u = np.zeros((2, 4, 2))
    u[0, :, 0] = [1.0, 1.0, 0.5, 1.0]
    u[1, :, 0] = [0.5, 0.5, 2.0, 0.5]
    index, unit = held_window_levels(u, np.array([0.1, 0.0]), [{1.0: 100, 0.5: 25, 2.0: 4}, {}])
    np.testing.assert_allclose(unit, [0.02, 0.01])  # 0.5 and 1.0; 2.0 (4 samples) is no held level
    np.testing.assert_array_equal(index[..., 0], [[1, 1, 0, 1], [0, 0, -1, 0]])
    np.testing.assert_array_equal(index[..., 1], -1)


def test_a_single_precision_fit_ends_with_float64_normal_equations(truth, monkeypatch):
    """With float32 coefficient tangents the steps come from float32 Jacobians, but the Hessian a fit
    returns (pruning, covariance) is computed again in float64 at its last point; the fit pulls
    perturbed coefficients towards the data, but not as close as a float64 fit."""
    from pisml_ros.ident import trajfit

    model, plant = truth
    data, start, weights = _perturbed_problem(model, plant, seed=4, duration=0.004, spread=0.01, rng_seed=2)
    passes = []
    normal_equations = trajfit._ShootingProblem.normal_equations

    def spy(problem, theta, z):
        passes.append(problem.single_precision)
        return normal_equations(problem, theta, z)

    monkeypatch.setattr(trajfit._ShootingProblem, "normal_equations", spy)
    fitter = trajfit.TrajectoryFitter(model._terms, 13, data.dt, window=10, substeps=2, weights=weights,
                                      single_precision=True)
    result = fitter.fit(start, model.coefficients != 0, data, lambda_jac=0.0, max_nfev=5)
    assert passes[:-1] and all(passes[:-1]) and passes[-1] is False
    assert result.accepted > 0 and result.hessian is not None and result.hessian.dtype == np.float64
    assert _replay_error(model, result.coefficients, data) < 0.5 * _replay_error(model, start, data)
    # float64 passes only: on these clean records the same budget gets far closer (measured 7e-9 against
    # 4.5e-4, the start 0.021; on stop 75's machine 6.9e-9 against 3.8e-6: float32 arithmetic differs
    # between CPUs, so the bound is 100x): steps from a float32 Jacobian stall far above float64's floor
    passes.clear()
    double = trajfit.TrajectoryFitter(model._terms, 13, data.dt, window=10, substeps=2, weights=weights).fit(
        start, model.coefficients != 0, data, lambda_jac=0.0, max_nfev=5)
    assert passes and not any(passes)
    assert _replay_error(model, double.coefficients, data) < 1e-2 * _replay_error(model, result.coefficients, data)


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


def _stability_prior_case(truth):
    """The stability prior's shooting problem at the true coefficients: two clean training records
    and two small-signal records at ug 0.8, weight 4, margin 1 1/s (the plant's slowest pair there is
    -0.73 ± 1.7j: both count); the problem, θ, and (fitter, start, data, small)."""
    from pisml_ros.ident.trajfit import TrajectoryFitter, _ShootingProblem

    model, plant = truth
    data, start, weights = _perturbed_problem(model, plant, seed=4, duration=0.002, spread=0.0, rng_seed=2)
    small = generate(plant, *schedules_for("smallsignal", n_traj=2, duration=0.008))
    fitter = TrajectoryFitter(model._terms, 13, data.dt, window=4, substeps=2, weights=weights)
    problem = _ShootingProblem(fitter, start, start != 0, data, small, lambda_jac=1.0, ss_stride=5,
                               lambda_stab=4.0, stability_margin=1.0)
    return problem, start.ravel()[problem.idx] / problem.scale, (fitter, start, data, small)


def test_stability_prior_residuals_are_the_eigenvalues_beyond_the_margin(truth):
    """At the small-signal operating point the prior's residuals are sqrt(w)·(Re λ + margin) of the
    eigenvalues of the model's Jacobian there with Re λ > -margin, and its θ-derivatives match
    central differences (first-order eigenvalue perturbation)."""
    from pisml_ros.data.dataset import steady_start_length
    from pisml_ros.ident.trajfit import _ShootingProblem

    problem, theta, (fitter, start, data, small) = _stability_prior_case(truth)
    res, jac = problem._stability_residuals(theta)
    tr = next(iter(small))
    rest = tr.x[:steady_start_length(tr)].mean(axis=0)
    eig = np.linalg.eigvals(truth[0].jacobian(rest, tr.u[0]))
    expected = np.sort(2.0 * (eig.real[eig.real > -1.0] + 1.0))
    assert res.size == 2
    np.testing.assert_allclose(np.sort(res), expected, rtol=1e-8)
    numeric = np.zeros_like(jac)
    for i in range(theta.size):
        step = np.zeros_like(theta)
        step[i] = 1e-6
        numeric[:, i] = (problem._stability_residuals(theta + step)[0]
                         - problem._stability_residuals(theta - step)[0]) / 2e-6
    np.testing.assert_allclose(jac, numeric, atol=1e-5 * np.abs(jac).max())
    # stable beyond the margin: no residuals; weight 0: the prior is off
    assert _ShootingProblem(fitter, start, start != 0, data, small, 1.0, 5, 4.0, 0.1)._stability_residuals(theta)[0].size == 0
    assert _ShootingProblem(fitter, start, start != 0, data, small, 1.0, 5, 0.0, 1.0)._stability_residuals(theta)[0].size == 0


def test_stability_prior_has_no_derivative_for_a_defective_eigenvalue(truth, monkeypatch):
    """An eigenvalue whose left and right eigenvectors are orthogonal (a Jordan block: a repeated
    eigenvalue of a model whose pruned rows couple only one way) has no derivative: the prior keeps
    its residual with a zero derivative row instead of the 1/(uᴴv) blow-up (inf or NaN there ends
    the whole Gauss-Newton loop). The eigen-decomposition is made defective for the slowest mode."""
    import scipy.linalg

    problem, theta, _ = _stability_prior_case(truth)
    res, jac = problem._stability_residuals(theta)
    eig = scipy.linalg.eig

    def defective(a, left, right):
        lam, u, v = eig(a, left=True, right=True)
        k = int(np.argmax(lam.real))
        w = u[:, k] - v[:, k] * (v[:, k].conj() @ u[:, k])  # u's part orthogonal to v
        u[:, k] = w / np.linalg.norm(w)
        return lam, u, v

    monkeypatch.setattr(scipy.linalg, "eig", defective)
    res_d, jac_d = problem._stability_residuals(theta)
    assert np.all(np.isfinite(jac_d))
    np.testing.assert_allclose(res_d, res, rtol=1e-12)  # the residuals are the eigenvalues, as before
    changed = np.any(jac_d != jac, axis=1)
    assert changed.sum() == len(problem.rest_gradients)  # the slowest mode at each anchoring rest state
    assert np.all(jac_d[changed] == 0.0) and np.any(jac[changed] != 0.0)


def test_equilibrium_prior_residuals_are_the_field_at_the_rest_states(truth):
    """The equilibrium prior's residuals are sqrt(w)·f(x_rest, u)/σ per equation at each anchoring rest
    state (σ: the noise left in the rest mean, through the start model's Jacobian), linear in θ with
    the derivatives it reports; at the true model they are small, off it they are not."""
    from pisml_ros.ident.trajfit import _ShootingProblem

    model, data, fitter, problem, start, small, weights, rest, samples = _equilibrium_prior_case(truth, "rates")
    theta = start.ravel()[problem.idx] / problem.scale
    res, jac = problem._equilibrium_residuals(theta)
    # both small-signal records sit at ug 0.8 before their steps: one rest state
    assert res.shape == (13,) and jac.shape == (13, theta.size)
    tr0 = next(iter(small))
    sigma = np.sqrt(model.jacobian(rest, tr0.u[0]) ** 2 @ (1 / weights) ** 2 / samples)
    np.testing.assert_allclose(res, 2.0 * model.vector_field(rest[None], tr0.u[:1])[0] / sigma, rtol=1e-8, atol=1e-8)
    assert np.abs(res).max() < 1.0  # the plant sat at its equilibrium: f there is ~0
    step = np.zeros_like(theta)
    step[:5] = 1e-3
    np.testing.assert_allclose(problem._equilibrium_residuals(theta + step)[0], res + jac @ step, rtol=1e-9, atol=1e-9)
    off = theta.copy()
    off[0] *= 1.01
    assert np.abs(problem._equilibrium_residuals(off)[0]).max() > 10.0
    # weight 0: the prior is off
    assert _ShootingProblem(fitter, start, start != 0, data, small, 1.0, 5)._equilibrium_residuals(theta)[0].size == 0


def test_term_gradients_by_the_product_rule_match_autodiff():
    import torch

    from pisml_ros.model.expressions import TermSet

    signals = STATE_NAMES + INPUT_NAMES
    z = torch.tensor(np.random.default_rng(3).normal(size=(6, len(signals))))
    # plans of degree 3, 2 (the shortcut for two factors) and 1, and none
    for terms in (["1", "il_d", "Pf*vc_q", "ig_d**2", "ug*cos(theta_g - delta)", "sin(delta)**2*il_q"],
                  ["1", "il_d", "Pf*vc_q", "vc_d**2", "ug*sin(delta - theta_g)", "cos(delta)"],
                  ["1", "il_d", "cos(delta)"],
                  ["1", "il_d", "il_d*(Pf - 0.5)", "(Pf - 0.5)**2", "ig_q*(Pf - 0.5)"],  # affine factors as written
                  ["vc_d*ig_d + vc_q*ig_q", "tanh(il_d)", "ug*sin(theta_g - delta)", "Abs(il_q)"],  # no product plan
                  # no product plan, sympy's derivatives: constant ones (2, -1, 0) from the fixed table
                  ["1", "2*Pf - il_d", "vc_d*ig_d + vc_q*ig_q", "il_q/(1 + il_q**2)", "ug*sin(theta_g - delta)"]):
        ts = TermSet(terms, signals)
        expected = torch.func.vmap(torch.func.jacfwd(ts.evaluate_torch))(z)
        np.testing.assert_allclose(ts.gradient_torch(z).numpy(), expected.numpy(), atol=1e-12)
        np.testing.assert_allclose(ts.gradient_torch(z[0]).numpy(), ts.gradient(z[0].numpy()), atol=1e-12)
        values, gradient = ts.values_and_gradient_torch(z)
        assert torch.equal(values, ts.evaluate_torch(z)) and torch.equal(gradient, ts.gradient_torch(z))
    assert TermSet(["1", "il_d*(Pf - 0.5)"], signals)._torch_plan()
    # without a product plan, sympy's derivatives run in torch where they are plain tensor
    # operations (thread-safe); Abs's derivative is not, and autodiff takes it
    assert TermSet(["vc_d*ig_d + vc_q*ig_q", "tanh(il_d)", "il_q/(1 + il_q**2)"], signals).thread_safe_gradient()
    assert not TermSet(["vc_d*ig_d + vc_q*ig_q", "Abs(il_q)"], signals).thread_safe_gradient()


def test_term_values_by_the_product_plan_match_the_generated_functions():
    """Rows of points go through the product plan (one gather and product); a single point and term
    sets without a plan through sympy's generated function. Terms of degree up to 2 give the same
    values to the bit (a refinement's selection replays its candidates on them)."""
    from pisml_ros.model.expressions import TermSet

    signals = STATE_NAMES + INPUT_NAMES
    z = np.random.default_rng(5).normal(size=(3, 8, len(signals)))
    for terms, exact in ((["1", "il_d", "Pf*vc_q", "vc_d**2", "ug*cos(theta_g - delta)", "cos(delta)"], True),
                         (["1", "il_d", "il_d*(Pf - 0.5)", "(Pf - 0.5)**2"], True),
                         (["1", "Pf*ig_q*vc_d", "sin(delta)**2*il_q"], False)):
        ts = TermSet(terms, signals)
        values = ts.evaluate(z)
        assert ts._numpy_gather, terms
        single = np.array([[ts.evaluate(point) for point in row] for row in z])  # no plan for one point
        if exact:
            assert np.array_equal(values, single), terms
        np.testing.assert_allclose(values, single, rtol=1e-14, atol=1e-14)
    plain = TermSet(["vc_d*ig_d + vc_q*ig_q", "tanh(il_d)"], signals)
    np.testing.assert_allclose(plain.evaluate(z)[1, 2], plain.evaluate(z[1, 2]), rtol=1e-15)
    assert plain._numpy_gather is False


def test_terms_with_numbers_inside_functions_evaluate_in_torch():
    """A model JSON may hold terms whose generated code hands a plain number to a function
    (sqrt(2)*x calls sqrt(2); Min(x, 1) passes 1): torch's functions reject those, so the
    compiled functions take them (the numpy path always did)."""
    import torch

    from pisml_ros.model.expressions import TermSet

    signals = STATE_NAMES + INPUT_NAMES
    terms = ["sqrt(2)*il_d", "Min(il_d, 1)", "Max(0.5, il_q)", "exp(-1)*vc_d + cos(1)*ig_q", "Abs(il_q) + sign(-2)"]
    ts = TermSet(terms, signals)
    z = np.random.default_rng(4).normal(size=(7, len(signals)))
    np.testing.assert_allclose(ts.evaluate_torch(torch.tensor(z)).numpy(), ts.evaluate(z), rtol=1e-14, atol=1e-14)
    gradient = ts.gradient_torch(torch.tensor(z)).numpy()
    np.testing.assert_allclose(gradient[:, 0, signals.index("il_d")], np.sqrt(2), rtol=1e-14)
    np.testing.assert_allclose(gradient[:, 1, signals.index("il_d")], (z[:, signals.index("il_d")] < 1).astype(float))


LIMITER_TERM = ("(0.5 + 1.2*il_d - 0.3*vc_q + 0.2*ig_d)"
                "*Min(1, 2.2/sqrt((0.5 + 1.2*il_d - 0.3*vc_q + 0.2*ig_d)**2 + (0.1*ig_q - 0.4*Pf + 0.7*il_q)**2))")


@pytest.mark.parametrize("terms, exact", [
    (["1", "il_d", "il_d*vc_q", "vc_d**2", "Pf*ig_q*vc_d", "ug*cos(theta_g - delta)", "ug*cos(theta_g - delta)*il_q"],
     True),
    (["1", "il_d", "ig_q**3", "Pf**2*vc_d**2"], True),  # no other factors
    (["vc_d*ig_d + vc_q*ig_q", "ug*sin(theta_g - delta)"], True),  # no product plan: a sum is a factor of its own
    # sums, a quotient, a number, a limiter's term and products of degree 3 in one set without a plan (the
    # generated function's common subexpressions group vc_d*ig_q of Pf*ig_q*vc_d first; the affine sums
    # of the limiter's term come from a matrix product): equal to rounding
    (["1", "il_d", "vc_d*ig_d + vc_q*ig_q", "vc_q*ig_d - vc_d*ig_q", "il_d/(1 + il_d**2)", "2*il_q", "Pf*ig_q*vc_d",
      LIMITER_TERM, "il_q**5", "ug*cos(theta_g - delta)*il_q"], False),
    (["1", "il_d", "Pf*vc_q", LIMITER_TERM], False),  # a product plan, with affine sums
])
def test_split_evaluation_gives_the_terms_to_the_bit(terms, exact):
    """The refinement's passes evaluate the terms from the states and the inputs apart
    (TermSet.evaluate_split_torch): the values, and the field Θ·C from them, are those of
    evaluate_torch on the joined signals exactly, so that a faster pass leaves every fit as it was
    (to rounding where a term set holds sums and products of three factors, or a limiter's terms)."""
    import torch

    from pisml_ros.model.expressions import TermSet

    signals = STATE_NAMES + INPUT_NAMES
    n = len(STATE_NAMES)
    rng = np.random.default_rng(3)
    ts = TermSet(terms, signals)
    c = torch.tensor(rng.normal(size=(len(terms), n)))
    for rows in (1, 48, 480, 48):  # (the cached ones of a count used before)
        y, u = torch.tensor(rng.normal(size=(rows, n))), torch.tensor(rng.normal(size=(rows, len(INPUT_NAMES))))
        joined = ts.evaluate_torch(torch.cat([y, u], dim=-1))
        split = ts.evaluate_split_torch(y, u)
        assert split.shape == (rows, len(terms))
        # the forward values of the tangent passes (values_and_jacobian_torch) are the split ones
        values, _ = ts.values_and_jacobian_torch(torch.cat([y, u], dim=-1), c, n)
        assert torch.equal(values, split)
        if exact:
            assert torch.equal(split, joined) and torch.equal(split @ c, joined @ c)
        else:
            torch.testing.assert_close(split, joined, rtol=1e-14, atol=1e-14)
    assert bool(ts._torch_plan()) == ("vc_d*ig_d + vc_q*ig_q" not in terms)


@pytest.mark.parametrize("terms", [
    ["1", "il_d", "il_d*vc_q", "vc_d**2", "Pf*ig_q*vc_d", "ug*cos(theta_g - delta)", "ug*sin(theta_g - delta)"],
    ["vc_d*ig_d + vc_q*ig_q", "vc_q*ig_d - vc_d*ig_q", "tanh(il_q)", "il_d/(1 + il_d**2)", "ug"],
    ["vc_d*ig_d + vc_q*ig_q", "Min(il_d, 1)"],  # a derivative torch cannot run here: the full gradients
])
def test_field_jacobian_in_torch_matches_the_term_gradients(terms):
    """values_and_jacobian_torch contracts only the terms' varying state derivatives with C; it
    must give what the full term gradients (numpy, sympy's derivatives) contracted with C give."""
    import torch

    from pisml_ros.model.expressions import TermSet

    signals = STATE_NAMES + INPUT_NAMES
    n = len(STATE_NAMES)
    rng = np.random.default_rng(7)
    ts = TermSet(terms, signals)
    z = rng.normal(size=(11, len(signals)))
    c = rng.normal(size=(len(terms), n)) * (rng.random((len(terms), n)) < 0.5)
    values, jac = ts.values_and_jacobian_torch(torch.tensor(z), torch.tensor(c), n)
    expected = np.einsum("pts,tj->pjs", ts.gradient(z)[..., :n], c)
    np.testing.assert_allclose(values.numpy(), ts.evaluate(z), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(jac.numpy(), expected, rtol=1e-12, atol=1e-12)
    assert jac.shape == (11, n, n)


def test_split_evaluation_of_two_state_counts_from_threads_at_once():
    """The shooting windows' threads evaluate one term set at once; with two state counts in use (a
    plan each) every call gives what a call alone gives. Stop 92: the plan's single slot, rebuilt
    for the other count, was read half-replaced (IndexError, or other terms' values)."""
    from concurrent.futures import ThreadPoolExecutor

    import torch

    from pisml_ros.model.expressions import TermSet

    signals = STATE_NAMES + INPUT_NAMES
    n = len(STATE_NAMES)
    ts = TermSet(["1", "il_d", "il_d*vc_q", "Pf*ig_q*vc_d", "ug*cos(theta_g - delta)", "ug*theta_g"], signals)
    rng = np.random.default_rng(5)
    z = torch.tensor(rng.normal(size=(64, len(signals))))
    alone = {k: ts.evaluate_split_torch(z[:, :k], z[:, k:]) for k in (n, n + 1)}

    def wrong(i):
        k = (n, n + 1)[i % 2]
        try:
            return not torch.equal(ts.evaluate_split_torch(z[:, :k], z[:, k:]), alone[k])
        except IndexError:
            return True

    # (the single slot: 22-34 wrong calls of 2000 on 8 threads, measured three times)
    with ThreadPoolExecutor(max_workers=8) as pool:
        assert sum(pool.map(wrong, range(2000))) == 0


def test_uncertainty_note_speaks_only_where_the_verdict_is_open():
    from pisml_ros.analysis.operating_point import uncertainty_note

    assert uncertainty_note(None) == ""
    assert uncertainty_note({"verdict": "stable", "max_real_interval": [-0.9, -0.5]}) == ""
    assert uncertainty_note({"verdict": "undetermined", "max_real_interval": [-0.3141, 0.05]}) == (
        "not decided by the data: max real part -0.314 .. 0.05 1/s, 2 std")


def test_data_coverage_flags_operating_points_outside_the_training_inputs():
    from pisml_ros.analysis.operating_point import coverage_note, data_coverage
    from pisml_ros.plant import InverterPlant

    model = ExplicitModel(["x"], ["ug", "theta_g"], ["x", "ug"], [[-1.0], [1.0]],
                          {"training": {"input_range": {"ug": [0.64, 1.2], "theta_g": [-0.17, 0.17]}},
                           "config": {"roles": {"grid_phase": "theta_g"}}})
    inside = data_coverage(model, (0.8, 1.0))  # the phase is relative to the inverter's angle: never flagged
    assert inside == {"input_range": {"ug": [0.64, 1.2]}, "outside": [], "extrapolated": False}
    assert coverage_note(inside) == ""
    outside = data_coverage(model, (0.4, 0.0))
    assert outside["extrapolated"] is True and outside["outside"] == ["ug"]
    assert coverage_note(outside) == "extrapolated: outside the identification data's ug 0.64-1.2"
    assert data_coverage(model, (1.2, 0.0))["extrapolated"] is False  # the range's ends are covered
    # models from before the range was recorded, and the plant, carry none
    assert data_coverage(ExplicitModel(["x"], ["ug", "theta_g"], ["x"], [[-1.0]]), (0.4, 0.0)) is None
    assert data_coverage(InverterPlant(), (0.4, 0.0)) is None


def test_the_report_names_a_second_equilibrium_near_the_records():
    from pisml_ros.analysis.operating_point import operating_point_report, other_equilibria_note

    # dx/dt = -(x - 1)(x - 1.05) + (ug - 1): at ug 1 an unstable root at 1 and a stable one at 1.05
    # (a fold of the model's own at ug 1.000625), and a third root nowhere (one state, degree 2)
    def model(states):
        refs = [{"inputs": [1.0, 0.0], "state": [s]} for s in states]
        return ExplicitModel(["x"], ["ug", "theta_g"], ["1", "x", "x**2", "ug"], [[-2.05], [2.05], [-1.0], [1.0]],
                             {"reference_points": refs})

    report = operating_point_report(model([0.99, 1.07]), 1.0)
    assert report["operating_point"]["state"]["x"] == pytest.approx(1.0) and not report["stable"]
    [other] = report["other_equilibria"]
    assert other["distance"] == pytest.approx(0.05) and other["stable"] and other["max_real"] == pytest.approx(-0.05)
    assert other["state"] == {"x": pytest.approx(1.05)} and other["differs_most"] == ["x"]
    [line] = other_equilibria_note(report)
    assert line.startswith("another equilibrium of the model 0.05 away in state (most in x), stable (largest real "
                           "part -0.05 1/s)")
    # rest states that all lead to the same root: nothing else to say; the plant says nothing either
    assert "other_equilibria" not in operating_point_report(model([0.99]), 1.0)
    assert "other_equilibria" not in operating_point_report(InverterPlant(), 1.0)


def test_equilibrium_prior_in_states_is_the_newton_step_to_the_models_equilibrium(truth):
    """With ``equilibrium_space="states"`` the residuals are sqrt(w)·(J⁻¹f)(x_rest)·sqrt(samples)/noise:
    the distance from the rest state to the model's equilibrium in units of the noise left in the rest
    mean; their θ-derivatives (J held) match finite differences near the equilibrium; a slow-row
    error that is small in rates is large in states."""
    from pisml_ros.ident.trajfit import _ShootingProblem

    model, data, fitter, problem, start, small, weights, rest, samples = _equilibrium_prior_case(truth, "states")
    theta = start.ravel()[problem.idx] / problem.scale
    res, jac = problem._equilibrium_residuals(theta)
    assert res.shape == (13,) and jac.shape == (13, theta.size)
    tr0 = next(iter(small))
    newton = np.linalg.solve(model.jacobian(rest, tr0.u[0]), model.vector_field(rest[None], tr0.u[:1])[0])
    np.testing.assert_allclose(res, 2.0 * newton * np.sqrt(samples) * weights, rtol=1e-6, atol=1e-6)
    # the rest mean of clean records is the equilibrium: a few noise units at most
    assert np.abs(res).max() < 1.0
    numeric = np.zeros((13, 5))
    for i in range(5):
        step = np.zeros_like(theta)
        step[i] = 1e-7
        numeric[:, i] = (problem._equilibrium_residuals(theta + step)[0]
                         - problem._equilibrium_residuals(theta - step)[0]) / 2e-7
    np.testing.assert_allclose(jac[:, :5], numeric, rtol=1e-3, atol=1e-6 * np.abs(jac).max())
    # a 1 % error in a slow (integrator) row's coefficient: a large shift of the equilibrium
    off = theta.copy()
    slow = np.flatnonzero(problem.row_of.numpy() == STATE_NAMES.index("phi_d"))[0]
    off[slow] *= 1.01
    assert np.abs(problem._equilibrium_residuals(off)[0]).max() > 100.0
    with pytest.raises(ValueError, match="equilibrium_space must be rates or states"):
        _ShootingProblem(fitter, start, start != 0, data, small, 1.0, 5, lambda_eq=1.0, equilibrium_space="x")


def _equilibrium_prior_case(truth, space):
    """The true model's shooting problem with the equilibrium prior (weight 4) anchored at two
    small-signal records' shared rest state: (model, data, fitter, problem, start, small, weights, rest
    mean, samples averaged)."""
    from pisml_ros.data.dataset import steady_start_mean
    from pisml_ros.ident.trajfit import TrajectoryFitter, _ShootingProblem

    model, plant = truth
    data, start, weights = _perturbed_problem(model, plant, seed=4, duration=0.002, spread=0.0, rng_seed=2)
    small = generate(plant, *schedules_for("smallsignal", n_traj=2, duration=0.008))
    fitter = TrajectoryFitter(model._terms, 13, data.dt, window=4, substeps=2, weights=weights)
    problem = _ShootingProblem(fitter, start, start != 0, data, small, 1.0, 5, lambda_eq=4.0,
                               equilibrium_space=space)
    rests = [steady_start_mean(tr) for tr in small]
    return (model, data, fitter, problem, start, small, weights, np.mean([r for _, r in rests], axis=0),
            sum(n for n, _ in rests))


def test_a_saved_model_is_readable_as_a_plainly_written_file_would_be(tmp_path):
    import os

    from pisml_ros.fileio import atomic_write_text

    path = ExplicitModel(["x"], ["ug", "theta_g"], ["x"], [[-1.0]]).save(tmp_path / "m.json")
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    assert path.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777  # not the temporary file's 0600
    os.chmod(path, 0o640)  # an existing file keeps its own
    assert atomic_write_text(path, "{}").stat().st_mode & 0o777 == 0o640


def test_a_replay_keeps_what_came_before_a_divergence_and_a_fits_batch_does_not():
    from pisml_ros.data import Dataset, Trajectory
    from pisml_ros.integrate import simulate_many

    # dx/dt = x^2 from x = 1 blows up at t = 1: the samples before stay, NaN from the blow-up on
    model = ExplicitModel(["x"], ["ug", "theta_g"], ["x**2"], [[1.0]])
    t = np.arange(20) * 0.1
    data = Dataset(("x",), ("ug", "theta_g"), [Trajectory(0, t, np.ones((20, 1)), np.ones((20, 2)))], {"dt": 0.1})
    pred = model.simulate(data).trajectories[0].x[:, 0]
    assert pred[5] == pytest.approx(1 / (1 - 0.5), rel=1e-4) and np.all(np.isfinite(pred[:9]))
    assert np.all(np.isnan(pred[11:]))
    # a fit's batch sees the run as one failure: NaN throughout
    [batch] = simulate_many(model, [np.ones(1)], [np.ones((20, 2))], 0.1)
    assert np.all(np.isnan(batch))



def test_records_of_different_lengths_run_in_one_pass_as_each_would_alone():
    from pisml_ros.integrate import simulate_many

    model = ExplicitModel(["x"], ["ug", "theta_g"], ["x", "ug", "x**2"], [[-3.0], [2.0], [0.1]])
    rng = np.random.default_rng(1)
    inputs = [rng.uniform(0.5, 1.5, size=(n, 2)) for n in (7, 20, 13)]
    starts = [np.array([0.1]), np.array([0.4]), np.array([-0.2])]
    for got, start, u in zip(simulate_many(model, starts, inputs, 1e-2), starts, inputs):
        [alone] = simulate_many(model, [start], [u], 1e-2)
        assert got.shape == (len(u), 1) and np.array_equal(got, alone)
    # dx/dt = x^2 from 1 blows up at t = 1: a record that ends before it is whole, though the
    # longer record it runs beside holds its last input on past the blow-up
    growing = ExplicitModel(["x"], ["ug", "theta_g"], ["x**2"], [[1.0]])
    short, long_ = simulate_many(growing, [np.ones(1), np.full(1, 0.01)], [np.ones((5, 2)), np.ones((20, 2))], 0.1)
    assert short.shape == (5, 1) and np.all(np.isfinite(short)) and np.all(np.isfinite(long_))

def test_the_alternatives_rebuild_from_the_json_and_say_whether_the_verdict_is_open(tmp_path, truth):
    from pisml_ros.analysis.operating_point import alternatives_note, operating_point_report
    from pisml_ros.ident.selection import alternative_entry

    model, _ = truth
    # a rival with a leaky voltage integrator turned into a growing one, and a copy of the model
    rival = ExplicitModel(model.state_names, model.input_names, model.terms + ["phi_d"],
                          np.vstack([model.coefficients, np.eye(13)[3] * 40.0]))
    chosen = ExplicitModel(model.state_names, model.input_names, model.terms, model.coefficients,
                           dict(model.metadata, alternatives=[alternative_entry("same", model, 2.0)]))
    path = chosen.save(tmp_path / "m.json")
    loaded = ExplicitModel.load(path)
    (name, same), = loaded.alternatives()
    assert name == "same" and np.allclose(same.vector_field(*_sample(model)), model.vector_field(*_sample(model)))
    # only the terms it uses are written
    assert len(loaded.metadata["alternatives"][0]["terms"]) == int(np.any(model.coefficients != 0, axis=1).sum())
    report = operating_point_report(loaded, 1.0)
    assert report["alternatives"]["agree"] and alternatives_note(report["alternatives"]) == ""
    chosen.metadata["alternatives"].append(alternative_entry("rival", rival, 2.1))
    report = operating_point_report(chosen, 1.0)
    assert report["stable"] and not report["alternatives"]["agree"]
    assert report["alternatives"]["candidates"][1]["max_real"] > 0
    assert alternatives_note(report["alternatives"]).startswith("stability not decided by the records: 2 candidate(s)")
    # a malformed entry is named, not a crash deep inside
    chosen.metadata["alternatives"] = [{"name": "x", "terms": ["phi_d"], "coefficients": [[1.0, 2.0]]}]
    with pytest.raises(ModelFormatError, match=r"metadata.alternatives\[0\]: field coefficients has shape"):
        chosen.alternatives()
    # ... and the report on the model itself stands, saying so
    report = operating_point_report(chosen, 1.0)
    assert report["stable"] and "metadata.alternatives[0]" in report["alternatives"]["error"]
    assert alternatives_note(report["alternatives"]).startswith("the model's alternatives could not be read")



def test_max_real_near_is_one_alternative_verdict_and_none_without_an_equilibrium():
    from pisml_ros.analysis.operating_point import max_real_near

    decaying = ExplicitModel(["x"], ["ug", "theta_g"], ["x", "ug"], [[-2.0], [1.0]])
    assert max_real_near(decaying, np.zeros(1), (0.8, 0.0)) == pytest.approx(-2.0)
    # dx/dt = 1 + x^2 has no real equilibrium: no verdict, not an error
    nowhere = ExplicitModel(["x"], ["ug", "theta_g"], ["1", "x**2"], [[1.0], [1.0]])
    assert max_real_near(nowhere, np.zeros(1), (0.8, 0.0)) is None

def _sample(model):
    rng = np.random.default_rng(0)
    return rng.normal(size=(5, model.n_states)), rng.normal(size=(5, 2))


def test_rest_window_starts_are_the_rest_means_of_the_windows_inside_a_steady_start():
    from pisml_ros.data import Dataset
    from pisml_ros.data.dataset import Trajectory
    from pisml_ros.ident.derivatives import rest_window_starts, trajectory_windows

    t = np.arange(60) * 1e-4
    x = np.ones((60, 2)) + np.where(t[:, None] >= 30e-4, 0.1, 0.0)  # at rest for 30 samples, then a step
    u = np.where(t[:, None] >= 30e-4, 1.0, 0.0)
    noise = 1e-3 * np.random.default_rng(1).standard_normal((60, 2))
    rest = Trajectory(0, t, x + noise, u)
    moving = Trajectory(1, t, x + t[:, None], u + t[:, None])  # never at rest
    data = Dataset(["a", "b"], ["ug"], [rest, moving], {"dt": 1e-4})
    targets, samples = rest_window_starts(data, 10)
    assert len(targets) == len(trajectory_windows(data, 10)[0]) == 10
    # windows from samples 0 and 10 lie inside the rest (samples 0-29), the one from 20 ends past it
    np.testing.assert_array_equal(samples, [30, 30, 0, 0, 0, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(targets[:2], np.repeat(rest.x[:30].mean(axis=0)[None], 2, axis=0))
    assert np.isnan(targets[2:]).all()
    # the same thinning as the windows'
    thinned, thinned_samples = rest_window_starts(data, 10, max_windows=4)
    assert len(thinned) == len(trajectory_windows(data, 10, max_windows=4)[0]) == 4
    np.testing.assert_array_equal(thinned_samples, [30, 0, 0, 0])


@pytest.mark.parametrize("threads", [1, 2])
def test_the_rest_start_prior_holds_the_rest_windows_starts_at_the_rest_mean(truth, threads):
    """With ``rest_starts`` the windows inside a record's steady start get a prior of precision
    rest_starts·samples/(window + 1) on their start offsets, centred where the start is the rest
    mean: the cost and the start-state blocks add it, the coefficients' blocks stay as they were,
    and fitting the starts alone moves those windows' starts to the rest mean."""
    import torch

    from pisml_ros.data import Dataset
    from pisml_ros.data.dataset import Trajectory, steady_start_mean
    from pisml_ros.ident.trajfit import TrajectoryFitter, _ShootingProblem

    model, plant = truth
    small = generate(plant, *schedules_for("smallsignal", n_traj=2, duration=0.008))
    rng = np.random.default_rng(0)
    noisy = Dataset(small.state_names, small.input_names,
                    [Trajectory(tr.traj_id, tr.t, tr.x + 1e-3 * rng.standard_normal(tr.x.shape), tr.u) for tr in small],
                    dict(small.metadata))
    weights = np.full(13, 1e3)
    start = model.coefficients * (1 + 0.01 * rng.standard_normal(model.coefficients.shape))

    def problem(rest_starts):
        fitter = TrajectoryFitter(model._terms, 13, noisy.dt, window=5, substeps=2, weights=weights, threads=threads,
                                  rest_starts=rest_starts)
        return _ShootingProblem(fitter, start, model.coefficients != 0, noisy, None, lambda_jac=0.0, ss_stride=5)

    free, held = problem(0.0), problem(2.0)
    assert free.rest_starts is None and held.rest_starts is not None and int((held.rest_starts[1] > 0).sum()) >= 4
    offsets, precision = held.rest_starts
    inside = precision[:, 0] > 0
    length = steady_start_mean(noisy.trajectories[0])[0]
    assert int(inside.sum()) == sum(steady_start_mean(tr)[0] // 5 - (steady_start_mean(tr)[0] % 5 == 0)
                                    for tr in noisy)
    assert float(precision[0, 0]) == pytest.approx(2.0 * length / 6)
    # the first window's offset takes its start to the rest mean
    rest = steady_start_mean(noisy.trajectories[0])[1]
    np.testing.assert_allclose((held.X[0, 0] + offsets[0] * held.x_unit).numpy(), rest, rtol=1e-12, atol=1e-12)
    theta = free.parameters(start)
    z = 0.1 * torch.randn((free.n_windows, 13), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    prior = 0.5 * float((precision * (z - offsets) ** 2).sum())
    assert held.cost(theta, z) == pytest.approx(free.cost(theta, z) + prior, rel=1e-12)
    a, b = free.normal_equations(theta, z), held.normal_equations(theta, z)
    prior_a = torch.diag_embed(precision.expand(-1, 13))
    np.testing.assert_allclose(b["A"].numpy(), (a["A"] + prior_a).numpy(), rtol=1e-12)
    np.testing.assert_allclose(b["bz"].numpy(), (a["bz"] + precision * (z - offsets)).numpy(), rtol=1e-12, atol=1e-12)
    for name in ("H", "g", "E"):
        np.testing.assert_allclose(b[name].numpy(), a[name].numpy(), rtol=1e-12)
    # the starts fitted alone: the rest windows' near the rest mean, nearer than without the prior
    z_free = free.fit_starts(theta, torch.zeros_like(z))
    z_held = held.fit_starts(theta, torch.zeros_like(z))
    assert float((z_held - offsets)[inside].abs().max()) < float((z_free - offsets)[inside].abs().max())
    free.close()
    held.close()
