"""Replay of measured trajectories through an identified model (explicit or neural)."""
from __future__ import annotations

from ..data import Dataset, Trajectory
from ..integrate import simulate_many


def replay(model, dataset: Dataset, substeps: int = 4, method: str = "rk4") -> Dataset:
    """Each trajectory's measured inputs, from its measured initial state, through ``model``.

    ``model`` needs ``state_names``, ``input_names`` and ``vector_field(x, u)`` (and ``jacobian``
    for the scipy methods); the dataset's columns are matched by name.

    Returns
    -------
    Dataset
        Predicted states on the same time grid (NaN from a divergence on; RK4 keeps the samples
        before it, :func:`~pisml_ros.integrate.simulate_many`).
    """
    cols = dataset.state_index(model.state_names)
    missing = [n for n in model.input_names if n not in dataset.input_names]
    if missing:
        raise ValueError(f"dataset lacks the model's input(s) {missing}")
    icols = [dataset.input_names.index(n) for n in model.input_names]
    preds = simulate_many(model, [tr.x[0, cols] for tr in dataset], [tr.u[:, icols] for tr in dataset],
                          dataset.dt, substeps=substeps, method=method, keep_before_divergence=True)
    out = [Trajectory(tr.traj_id, tr.t.copy(), p, tr.u[:, icols]) for tr, p in zip(dataset, preds)]
    return Dataset(tuple(model.state_names), tuple(model.input_names), out, {"dt": dataset.dt, "source": "simulation"})
