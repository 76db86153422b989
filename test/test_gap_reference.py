"""The gap workflow's references simulated together give each the predictions it gives alone."""
import numpy as np

from pisml_ros.data.dataset import concat_datasets
from pisml_ros.gap import ModelReference, PlantReference
from pisml_ros.gap.reference import simulate_references
from pisml_ros.model import ExplicitModel
from pisml_ros.plant import InverterPlant
from pisml_ros.plant.scenarios import generate, schedules_for
from pisml_ros.signals import INPUT_NAMES, STATE_NAMES


def test_references_together_give_what_each_gives_alone_on_any_trajectories():
    schedules, _ = schedules_for("test", seed=1)
    # records of two lengths, taken out of order: each length is its own stacked pass
    data = concat_datasets([generate(InverterPlant(), schedules, 0.01), generate(InverterPlant(), schedules, 0.02)])
    base = PlantReference()
    references = [base, base.with_effects({"current_limit": {"imax": 1.5}}),
                  ModelReference(ExplicitModel(STATE_NAMES, INPUT_NAMES, ["1"], np.zeros((1, 13)))),
                  base.with_effects({"delay": {"td": 2e-4}}), base.with_effects({"param_drift": {"Lg": 0.06}})]
    index = [3, 0, 2]
    together = simulate_references(references, data, substeps=1, traj_index=index)
    for reference, preds in zip(references, together):
        alone = reference.simulate(data, substeps=1, traj_index=index)
        assert [p.shape for p in preds] == [(len(data.trajectories[k].t), 13) for k in index]
        for p, q in zip(preds, alone):
            assert np.array_equal(p, q)
    assert not np.array_equal(together[0][0], together[3][0])  # the plants do differ


def test_references_with_the_same_unnamed_terms_are_stacked_with_them():
    schedules, _ = schedules_for("test", seed=1)
    data = generate(InverterPlant(), schedules, 0.01)
    coefficients = np.zeros((2, 13))
    coefficients[0, 1], coefficients[1, 11] = 0.3, -5.0  # d(Pf)/dt += 0.3, d(ig_d)/dt += -5·vc_d
    residual = ExplicitModel(STATE_NAMES, INPUT_NAMES, ["1", "vc_d"], coefficients)
    base = PlantReference().with_residual(residual)
    references = [base, base.with_effects({"param_drift": {"Lg": 0.06}})]
    together = simulate_references(references, data, substeps=1)
    for reference, preds in zip(references, together):
        for p, q in zip(preds, reference.simulate(data, substeps=1)):
            assert np.array_equal(p, q)
    without = PlantReference().simulate(data, substeps=1)
    assert not np.array_equal(together[0][0], without[0])  # the terms act


def test_a_long_record_is_simulated_a_few_plants_a_pass(monkeypatch):
    import pisml_ros.gap.reference as reference_module

    schedules, _ = schedules_for("test", seed=1)
    data = generate(InverterPlant(), schedules, 0.01)
    references = [PlantReference().with_effects({"param_drift": {"Lf": value}}) for value in (0.09, 0.1, 0.11)]
    whole = simulate_references(references, data, substeps=1)
    monkeypatch.setattr(reference_module, "_MAX_ROW_SAMPLES", 2 * len(data.trajectories[0].t))  # one plant a pass
    passes = []
    original = reference_module.PlantStack

    def counted(plants, rows):
        passes.append(len(plants))
        return original(plants, rows)

    monkeypatch.setattr(reference_module, "PlantStack", counted)
    chunked = simulate_references(references, data, substeps=1)
    assert passes == [1, 1, 1]
    assert all(np.array_equal(p, q) for a, b in zip(whole, chunked) for p, q in zip(a, b))
