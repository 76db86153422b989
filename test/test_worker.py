"""Identification in a child process (pisml_ros.ident.worker): results, cancel, a dying child."""
import os

import numpy as np
import pytest

from pisml_ros.ident import IdentConfig
from pisml_ros.ident.estimators import StageUpdate
from pisml_ros.ident.worker import IdentificationWorker, ModelSummary, RunResult
from pisml_ros.model import ExplicitModel
from pisml_ros.plant import InverterPlant
from pisml_ros.plant.scenarios import generate, schedules_for

FAST = {"epochs": 4, "batch_windows": 16, "distill_samples": 2000, "refine_max_nfev": 2, "refine_max_windows": 8,
        "refine_growing_evaluations": "2,2,2", "refine_polish_evaluations": "2,2",
        "distill_max_terms": 2}


@pytest.fixture(scope="module")
def train():
    return generate(InverterPlant(), *schedules_for("train", seed=3, n_traj=4, duration=0.02))


def test_a_run_in_a_child_process_reports_stages_and_the_model(train):
    worker = IdentificationWorker(threads=1)
    try:
        worker.submit("pisml", IdentConfig.from_mapping(FAST), train)
        items = list(worker.results())
    finally:
        worker.close()
    assert worker.pid != os.getpid()
    updates, result = items[:-1], items[-1]
    assert all(isinstance(u, StageUpdate) for u in updates)
    staged = {u.stage: u.model for u in updates if u.model is not None}
    assert isinstance(staged["backbone"], ExplicitModel)
    # the hybrid has no explicit form: its names, size and backbone cross the process boundary
    assert isinstance(staged["hybrid"], ModelSummary) and staged["hybrid"].n_parameters > 1000
    assert isinstance(staged["hybrid"].backbone, ExplicitModel)
    assert isinstance(result, RunResult) and result.status == "done", result.error
    assert isinstance(result.model, ExplicitModel) and result.model.metadata["stage"] == "explicit"
    assert result.metrics["seconds"] > 0 and "training" in result.history
    x, u = train.trajectories[0].x[:2], train.trajectories[0].u[:2]
    assert np.all(np.isfinite(result.model.vector_field(x, u)))
    with pytest.raises(RuntimeError, match="one job"):
        worker.submit("pisml", IdentConfig(), train)


def test_a_run_can_be_cancelled_and_the_process_ends(train):
    worker = IdentificationWorker(threads=1)
    seen = []
    worker.submit("pisml", IdentConfig.from_mapping(dict(FAST, epochs=200)), train)
    for item in worker.results(should_stop=lambda: any(u.stage == "training" for u in seen)):
        seen.append(item)
    worker.close()
    assert isinstance(seen[-1], RunResult) and seen[-1].status == "cancelled"
    assert not worker._process.is_alive()


def test_bad_input_and_a_killed_child_are_reported_not_raised(train):
    worker = IdentificationWorker(threads=1)
    worker.submit("pisml", {"epochs": 1, "roles": {"angle": "no_such_state"}}, train)
    result = list(worker.results())[-1]
    worker.close()
    assert result.status == "failed" and "no_such_state" in result.error
    worker = IdentificationWorker(threads=1)
    worker.submit("pisml", IdentConfig.from_mapping(dict(FAST, epochs=500)), train)
    items = worker.results()
    next(items)  # running
    worker._process.kill()
    result = [i for i in items if isinstance(i, RunResult)][0]
    worker.close()
    assert result.status == "failed" and "exit" in result.error
