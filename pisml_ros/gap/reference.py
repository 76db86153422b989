"""Reference models of the gap workflow: the virtual-HIL plant with nameplate parameters
(optionally augmented with effects), or an explicit model; both replay measured inputs
from each trajectory's measured initial state."""
from __future__ import annotations

import copy

import numpy as np

from ..data import Dataset
from ..integrate import simulate_many
from ..model import ExplicitModel
from ..plant import InverterPlant, PlantParameters
from ..plant.model import N_MEASURED
from ..plant.stack import PlantStack

def _with_residual(rates, residual: ExplicitModel | None, x, u):
    """A plant's rates plus an `unnamed` effect's explicit terms on its measured states."""
    if residual is None:
        return rates
    rates = rates.copy()
    rates[..., :N_MEASURED] += residual.vector_field(x[..., :N_MEASURED], u)
    return rates


# effects whose parameters are merged key by key when several are added (their keys name parameters)
_MERGED_EFFECTS = ("param_drift", "gain_mismatch")


class PlantReference:
    """The virtual HIL as a reference: nameplate parameters plus zero or more effects."""

    kind = "plant"

    def __init__(self, params: PlantParameters | None = None, effects: dict | None = None,
                 residual: ExplicitModel | None = None):
        self.params = params or PlantParameters()
        self.effects = copy.deepcopy(effects or {})
        self.residual = residual  # an `unnamed` effect: extra explicit terms added to the vector field
        self.plant = InverterPlant(self.params, self.effects)
        self.state_names = self.plant.state_names
        self.input_names = self.plant.input_names

    def with_effects(self, extra: dict) -> "PlantReference":
        """A new reference with more effects (param_drift / gain_mismatch entries are merged)."""
        effects = copy.deepcopy(self.effects)
        for name, values in extra.items():
            if name in _MERGED_EFFECTS and name in effects:
                effects[name].update(values)
            else:
                effects[name] = dict(values)
        return PlantReference(self.params, effects, self.residual)

    def with_residual(self, residual: ExplicitModel) -> "PlantReference":
        return PlantReference(self.params, self.effects, residual)

    def vector_field(self, x, u):
        return _with_residual(self.plant.vector_field(x, u), self.residual, x, u)

    def internal_signals(self, x, u) -> dict:
        return self.plant.internal_signals(self.plant.full_state(x, u), u)

    def simulate(self, dataset: Dataset, substeps: int = 2, traj_index=None) -> list[np.ndarray]:
        """Predicted measured states for each trajectory (list of (n, 13) arrays; NaN after a divergence)."""
        return _batch_simulate(self, dataset, substeps, traj_index, lambda tr: self.plant.full_state(tr.x[0], tr.u[0]))

    def describe(self) -> dict:
        return {"kind": "plant", "parameters": self.params.to_dict(), "effects": self.effects,
                "residual": self.residual.to_dict() if self.residual is not None else None}


class ModelReference:
    """An explicit model JSON as the reference."""

    kind = "model"

    def __init__(self, model: ExplicitModel, residual: ExplicitModel | None = None):
        self.model = model
        self.residual = residual
        self.state_names = model.state_names
        self.input_names = model.input_names
        self.effects = {}

    def vector_field(self, x, u):
        out = self.model.vector_field(x, u)
        return out + self.residual.vector_field(x, u) if self.residual is not None else out

    def with_residual(self, residual: ExplicitModel) -> "ModelReference":
        return ModelReference(self.model, residual)

    def internal_signals(self, x, u) -> dict:
        return {}

    def simulate(self, dataset: Dataset, substeps: int = 2, traj_index=None) -> list[np.ndarray]:
        return _batch_simulate(self, dataset, substeps, traj_index, lambda tr: tr.x[0])

    def describe(self) -> dict:
        return {"kind": "model", "model": self.model.to_dict(),
                "residual": self.residual.to_dict() if self.residual is not None else None}


# rows × samples of one stacked simulation (its states alone take ~140 bytes a row-sample)
_MAX_ROW_SAMPLES = 1_000_000


class _StackWithResidual:
    """A plant stack plus the references' common `unnamed` residual terms."""

    def __init__(self, stack: PlantStack, residual: ExplicitModel | None):
        self.stack, self.residual = stack, residual

    def vector_field(self, x, u):
        return _with_residual(self.stack.vector_field(x, u), self.residual, x, u)


def simulate_references(references, dataset: Dataset, substeps: int = 2, traj_index=None) -> list[list[np.ndarray]]:
    """Each reference's predictions (as its ``simulate`` gives them), all in one vectorised pass.

    Plant references with the same residual terms are simulated as one :class:`PlantStack` (the
    same numbers as one by one — Padé-2 delays aside, ~1e-14 apart — in about the time of one),
    at most ``_MAX_ROW_SAMPLES`` rows × samples a pass; any other reference on its own.
    """
    references = list(references)
    out: list = [None] * len(references)
    stackable = [i for i, ref in enumerate(references)
                 if isinstance(ref, PlantReference) and ref.residual is references[0].residual]
    for i, ref in enumerate(references):
        if i not in stackable or len(stackable) == 1:
            out[i] = ref.simulate(dataset, substeps=substeps, traj_index=traj_index)
    if len(stackable) < 2:
        return out
    index = list(traj_index if traj_index is not None else range(len(dataset)))
    per_length: dict[int, list[int]] = {}
    for k in index:
        per_length.setdefault(len(dataset.trajectories[k].u), []).append(k)
    preds = {i: {} for i in stackable}
    for length, members in per_length.items():
        trajs = [dataset.trajectories[k] for k in members]
        per_pass = max(1, _MAX_ROW_SAMPLES // (len(trajs) * length))  # long records: fewer plants a pass
        for first in range(0, len(stackable), per_pass):
            chunk = stackable[first:first + per_pass]
            stack = PlantStack([references[i].plant for i in chunk], [len(trajs)] * len(chunk))
            starts = stack.full_state(np.stack([tr.x[0] for _ in chunk for tr in trajs]),
                                      np.stack([tr.u[0] for _ in chunk for tr in trajs]))
            rows = simulate_many(_StackWithResidual(stack, references[chunk[0]].residual), list(starts),
                                 [tr.u for _ in chunk for tr in trajs], dataset.dt, substeps=substeps,
                                 n_out=len(dataset.state_names))
            for j, i in enumerate(chunk):
                preds[i].update(zip(members, rows[j * len(trajs):(j + 1) * len(trajs)]))
    for i in stackable:
        out[i] = [preds[i][k] for k in index]
    return out


def _batch_simulate(system, dataset: Dataset, substeps, traj_index, start_of) -> list[np.ndarray]:
    """Measured-state predictions of the selected trajectories, each from ``start_of(trajectory)``."""
    trajs = [dataset.trajectories[k] for k in (traj_index if traj_index is not None else range(len(dataset)))]
    return simulate_many(system, [start_of(tr) for tr in trajs], [tr.u for tr in trajs], dataset.dt,
                         substeps=substeps, n_out=len(dataset.state_names))
