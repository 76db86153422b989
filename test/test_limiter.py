"""The limit of a dq reference (its magnitude, or each axis) found in the records
(pisml_ros.ident.limiter) and what its terms need from the rest of the engine: torch gradients
through Min and Max, monomial basis, integrator rows, parameter count."""
import numpy as np
import pytest

from pisml_ros.ident import SignalRoles
from pisml_ros.ident.library import integrator_row_mask, monomial_basis
from pisml_ros.ident.limiter import (fit_reference_limit, is_limiter_term, limit_in_use, limit_note,
                                     limiter_terms, readable_equations)
from pisml_ros.model import ExplicitModel
from pisml_ros.model.expressions import TermSet
from pisml_ros.plant import InverterPlant
from pisml_ros.plant.scenarios import generate, training_schedules
from pisml_ros.signals import INPUT_NAMES, STATE_NAMES

SIGNALS = list(STATE_NAMES) + list(INPUT_NAMES)
IMAX = 2.2
CLAMP = (1.6, 2.4)
# the plant's effect, the kind of limit that matches it, its limits
LIMITS = [({"current_limit": {"imax": IMAX}}, "magnitude", (IMAX,)),
          ({"current_clamp": {"imax_d": CLAMP[0], "imax_q": CLAMP[1]}}, "clamp", CLAMP)]


def _records(effects, n_traj=12, seed=0):
    plant = InverterPlant(effects=effects or None)
    return plant, generate(plant, training_schedules(n_traj, seed, 0.04), 0.04)


@pytest.mark.parametrize("kind, limit", [("magnitude", 1.2), ("clamp", (1.2, 0.9))])
def test_limiter_terms_limit_the_reference_and_differentiate_in_numpy_and_torch(kind, limit):
    import torch

    terms = limiter_terms({"1": 0.5, "il_d": 2.0}, {"vc_q": -1.5}, limit, kind)
    assert all(is_limiter_term(t, SIGNALS) for t in terms) and not is_limiter_term("il_d*vc_q", SIGNALS)
    ts = TermSet(terms, SIGNALS)
    rng = np.random.default_rng(0)
    z = rng.normal(scale=0.8, size=(64, len(SIGNALS)))
    ld = 0.5 + 2.0 * z[:, SIGNALS.index("il_d")]
    lq = -1.5 * z[:, SIGNALS.index("vc_q")]
    if kind == "magnitude":
        scale = np.minimum(1.0, 1.2 / np.hypot(ld, lq))
        assert 0 < np.mean(scale < 1) < 1  # both sides of the limit
        np.testing.assert_allclose(ts.evaluate(z), np.column_stack([ld * scale, lq * scale]), rtol=1e-6)
        assert np.all(np.hypot(*ts.evaluate(z).T) <= 1.2 + 1e-6)
    else:
        clipped = np.column_stack([np.clip(ld, -1.2, 1.2), np.clip(lq, -0.9, 0.9)])
        assert 0 < np.mean(clipped[:, 0] != ld) < 1 and 0 < np.mean(clipped[:, 1] != lq) < 1
        np.testing.assert_allclose(ts.evaluate(z), clipped, rtol=1e-6)
    with pytest.raises(ValueError, match="limiter kind 'box'"):
        limiter_terms({"1": 0.5}, {"1": 0.5}, 1.0, "box")
    with pytest.raises(ValueError, match="limiter kind 'box'"):
        fit_reference_limit(None, kinds=("magnitude", "box"))  # before any work on the records
    # sympy writes the derivatives of Min and Max with Heaviside: torch's code must run on a batch of rows
    values, grad = ts.values_and_gradient_torch(torch.as_tensor(z))
    np.testing.assert_allclose(grad.numpy(), ts.gradient(z), rtol=1e-9, atol=1e-12)
    step = 1e-7
    k = SIGNALS.index("il_d")
    moved = z.copy()
    moved[:, k] += step
    np.testing.assert_allclose((ts.evaluate(moved) - ts.evaluate(z)) / step, ts.gradient(z)[..., k], atol=1e-4)


def test_limiter_terms_stay_whole_in_the_monomial_basis_enter_integrator_rows_and_count_their_constants():
    terms = ["1", "il_d", "vc_d*ig_d + vc_q*ig_q", *limiter_terms({"1": 0.5, "il_d": 2.0}, {"vc_q": -1.5}, 1.2)]
    basis, mapping = monomial_basis(terms, SIGNALS)
    assert basis[-2:] == terms[-2:] and mapping[-1, -1] == 1.0
    mask = integrator_row_mask(terms, STATE_NAMES, SIGNALS, SignalRoles())
    gamma = list(STATE_NAMES).index("gamma_d")
    assert list(mask[:, gamma]) == [True, True, False, True, True]
    coef = np.zeros((len(terms), len(STATE_NAMES)))
    coef[1, 0] = 1.0
    assert ExplicitModel(STATE_NAMES, INPUT_NAMES, terms, coef).n_parameters == 1
    coef[3, gamma] = coef[4, gamma] = 1.0
    # three coefficients, and the reference's three numbers and the limit, shared by both terms
    assert ExplicitModel(STATE_NAMES, INPUT_NAMES, terms, coef).n_parameters == 3 + 4
    # a clamp: the reference's three numbers and one limit per axis (its −m and m are one number)
    terms[-2:] = limiter_terms({"1": 0.5, "il_d": 2.0}, {"vc_q": -1.5}, (1.2, 0.9), "clamp")
    assert ExplicitModel(STATE_NAMES, INPUT_NAMES, terms, coef).n_parameters == 3 + 5


@pytest.mark.parametrize("kind, limit", [("magnitude", (2.2,)), ("clamp", (1.6, 2.4))])
def test_readable_equations_write_the_limited_reference_as_named_signals_that_define_the_same_field(kind, limit):
    import sympy

    argument = {"d": {"1": 0.5, "il_d": 2.0}, "q": {"vc_q": -1.5}}
    limited = limiter_terms(argument["d"], argument["q"], limit, kind)
    terms = ["1", "il_d", *limited, "Min(1.0, il_q)"]
    names = list(STATE_NAMES)
    coef = np.zeros((len(terms), len(names)))
    coef[1:3, names.index("gamma_d")] = [-1.0, 1.0]
    coef[3, names.index("gamma_q")] = 0.5
    coef[[0, 4], names.index("delta")] = [1.0, 2.0]
    record = {"kind": kind, "integrators": ["gamma_d", "gamma_q"], "measured": ["il_d", "il_q"], "argument": argument,
              "limit": list(limit), "saturated_fraction": 0.1, "misfit_reduction": 0.5, "terms": limited}
    model = ExplicitModel(STATE_NAMES, INPUT_NAMES, terms, coef, {"limiter": {"found": True, "limit": record}})
    lines = readable_equations(model, digits=6)
    equations, where = lines[:len(names)], lines[len(names):]
    assert equations[names.index("gamma_d")] == "d(gamma_d)/dt = -1*il_d + 1*S_d"
    assert equations[names.index("delta")] == "d(delta)/dt = 1 + 2*S1"
    written = {"magnitude": ["l_d*Min(1, 2.2/sqrt(l_d**2 + l_q**2))", "l_q*Min(1, 2.2/sqrt(l_d**2 + l_q**2))"],
               "clamp": ["Max(-1.6, Min(1.6, l_d))", "Max(-2.4, Min(2.4, l_q))"]}[kind]
    assert where == ["where l_d = 0.5 + 2.0*il_d", "where l_q = -1.5*vc_q", f"where S_d = {written[0]}",
                     f"where S_q = {written[1]}", "where S1 = Min(1.0, il_q)"]
    # the named equations with their definitions substituted are the model's own
    symbols = {s: sympy.Symbol(s) for s in SIGNALS}
    defined = {}
    for line in where:
        name, text = line[len("where "):].split(" = ", 1)
        known = {**symbols, **{str(k): k for k in defined}}
        defined[sympy.Symbol(name)] = sympy.sympify(text, locals=known).subs(defined)
    rng = np.random.default_rng(1)
    for _ in range(5):
        point = dict(zip(SIGNALS, rng.normal(scale=1.5, size=len(SIGNALS))))

        def at(expr):  # (by name: the model's symbols carry assumptions of their own)
            return float(expr.subs({symbol: point[str(symbol)] for symbol in expr.free_symbols}))

        for line, exact in zip(equations, model.sympy_equations()):
            rhs = sympy.sympify(line.split(" = ", 1)[1], locals={**symbols, **{str(k): k for k in defined}})
            assert at(rhs.subs(defined)) == pytest.approx(at(exact), rel=1e-9, abs=1e-12)
    # a record that does not say what the model's terms say: generic names, each term whole
    record["argument"] = {"d": {"1": 0.6, "il_d": 2.0}, "q": {"vc_q": -1.5}}
    assert readable_equations(model)[len(names):] == [f"where S{k + 1} = {t}" for k, t in enumerate(terms[2:])]
    # a limit found that the model does without: said, with what that means for its response
    unused = coef.copy()
    unused[2:4] = 0.0
    without = ExplicitModel(STATE_NAMES, INPUT_NAMES, terms, unused, model.metadata)
    note = limit_note(without)
    assert "the model chosen does not use it" in note and note.endswith("differ from the inverter's")
    assert limit_in_use(without) is False and limit_in_use(model) is True
    # no such term: the equations as they are
    plain = ExplicitModel(STATE_NAMES, INPUT_NAMES, terms[:2], coef[:2])
    assert readable_equations(plain, digits=4) == plain.equations(digits=4)
    assert limit_in_use(plain) is None and limit_note(plain) is None


@pytest.mark.slow
@pytest.mark.parametrize("effects, kind, limits", LIMITS)
def test_a_current_limit_is_found_in_the_records_where_it_acts_and_nowhere_else(effects, kind, limits):
    plant, records = _records(effects)
    found = fit_reference_limit(records)
    assert found is not None and found.kind == kind
    assert found.integrators == ("gamma_d", "gamma_q") and found.measured == ("il_d", "il_q")
    assert found.limit == pytest.approx(limits, rel=2e-3)
    assert found.misfit_reduction > 0.99
    # the limited reference, rebuilt from the terms alone, is the plant's
    x = np.concatenate([tr.x for tr in records])
    u = np.concatenate([tr.u for tr in records])
    inside = plant.internal_signals(x, u)
    limited = TermSet(found.terms(), SIGNALS).evaluate(np.concatenate([x, u], axis=1))
    truth = np.column_stack([inside["ilref_d"], inside["ilref_q"]])
    assert np.sqrt(np.mean((limited - truth) ** 2)) < 0.01 * np.sqrt(np.mean(truth ** 2))
    free = np.column_stack([inside["ilref_unlimited_d"], inside["ilref_unlimited_q"]])
    acting = np.hypot(*free.T) > IMAX if kind == "magnitude" else np.any(np.abs(free) > limits, axis=1)
    assert found.saturated_fraction == pytest.approx(np.mean(acting), abs=0.01)
    assert found.to_dict()["terms"] == found.terms()
    # what `pisml identify` prints and the identifier node logs for a model that uses the limit's terms
    coef = np.zeros((3, len(STATE_NAMES)))
    coef[1:, list(STATE_NAMES).index("gamma_d")] = 1.0
    model = ExplicitModel(STATE_NAMES, INPUT_NAMES, ["1", *found.terms()], coef,
                          {"limiter": {"run": True, "found": True, "limit": found.to_dict()}})
    said = {"magnitude": "a magnitude limit found in the records: gamma_d/gamma_q integrate a reference "
                         "limited to 2.2 minus il_d/il_q",
            "clamp": "a per-axis clamp found in the records: gamma_d/gamma_q integrate a reference "
                     "clamped to ±1.6 (d) and ±2.4 (q) minus il_d/il_q"}[kind]
    assert limit_note(model).startswith(said) and limit_note(model).endswith("the model uses it")
    if kind != "magnitude":
        return
    _, plain = _records({})
    assert fit_reference_limit(plain) is None
    assert limit_note(ExplicitModel(STATE_NAMES, INPUT_NAMES, ["1"], np.ones((1, len(STATE_NAMES))))) is None


@pytest.mark.slow
def test_pisml_finds_the_current_limit_its_libraries_lack_and_its_model_reproduces_the_saturated_tests(monkeypatch):
    # the magnitude limit (the engine's path does not depend on the kind; make bench-limits runs PISML on
    # the clamp too: 0.0227 / 0.142 % IOD / OOD clean, recording 0)
    import json

    from pisml_ros.analysis.metrics import protocol_errors
    from pisml_ros.ident import IdentConfig, make_estimator
    from pisml_ros.plant.scenarios import evaluation_schedules, smallsignal_schedules

    plant, records = _records({"current_limit": {"imax": IMAX}})
    small = generate(plant, smallsignal_schedules(0.8), 0.1)
    test = generate(plant, evaluation_schedules(0.04), 0.04)
    # (the tests' fast configuration, few evaluations in every refinement: 49 s against 73 s with the
    # stages' defaults, the same model)
    from fast_config import FAST
    from pisml_ros.ident import estimators

    real, refined = estimators.refine_explicit, set()

    def recorded(model, train, smallsignal, cfg, *args, **kwargs):
        refined.add((any("Min(" in term for term in model.terms), cfg.refine_rest_weight))
        return real(model, train, smallsignal, cfg, *args, **kwargs)

    monkeypatch.setattr(estimators, "refine_explicit", recorded)
    model = make_estimator("pisml", IdentConfig.from_mapping(FAST)).fit(records, small).explicit_model_
    record = model.metadata["limiter"]
    assert record["run"] and record["found"]
    assert record["limit"]["kind"] == "magnitude" and record["limit"]["limit"] == pytest.approx([IMAX], rel=2e-3)
    assert "with limit" in model.metadata["selection"]["chosen"]
    # the family ran before the unrestricted fallback and gave a model: no refinement without its terms
    assert model.metadata["refinement_unrestricted"]["superseded_by_limit"]
    assert not model.metadata["refinement_unrestricted"]["run"]
    # the family's polish holds its models' equilibria to the records' rest states
    # (IdentConfig.limiter_rest_weight); the fit's other families keep refine_rest_weight
    config = IdentConfig()
    assert refined == {(False, config.refine_rest_weight), (True, config.limiter_rest_weight)}
    assert config.limiter_rest_weight > 0 == config.refine_rest_weight
    assert limit_note(model).startswith("a magnitude limit found in the records: gamma_d/gamma_q integrate a "
                                        "reference limited to 2.2") and limit_note(model).endswith("the model uses it")
    assert not any("far worse" in warning for warning in model.metadata["selection"]["warnings"])
    assert sum("Min(" in t for t in model.terms) == 2
    assert model.n_parameters > np.count_nonzero(model.coefficients)
    # the phase jump and the sag to 0.4 p.u. both drive the plant into its limit (without the limit's
    # terms: 10.2 / 62.5 % IOD / OOD in the benchmark), and the JSON alone rebuilds the model
    again = ExplicitModel.from_dict(json.loads(model.to_json()))
    errors = protocol_errors(again, test)
    assert errors["iod"] < 0.5 and errors["ood"] < 2.0


def test_the_limits_family_supersedes_the_further_tries_only_where_one_of_its_refined_models_runs_through():
    from pisml_ros.ident.estimators import _limit_supersedes

    scores = {"re-fit +100 % with limit": 1.0, "refined with limit": 50.0, "pruned +0.1 % with limit": 12.0,
              "refined with limit from chosen with limit": float("inf")}
    record = {"run": True, "found": True, "family": True, "added": list(scores)}
    assert _limit_supersedes(record, scores, hold=40.0)  # a prune round beats holding the first states
    assert not _limit_supersedes(record, scores, hold=10.0)  # the re-fit is no refinement: it does not count
    assert not _limit_supersedes({**record, "added": ["refined with limit"]}, scores, hold=40.0)
    # no limit found, no family, no record
    assert not _limit_supersedes({"run": True, "found": False, "family": True}, scores, hold=40.0)
    assert not _limit_supersedes(None, scores, hold=40.0)
