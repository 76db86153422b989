"""Several virtual-HIL plants simulated as one vectorised system.

Each row of a state batch runs with its own plant's parameters and effects. The
gap workflow simulates dozens of candidate parameter values on the same few
records, and the vector field's cost is per call (numpy's overhead on a few
rows), not per row: one pass over all candidates costs about as much as one
candidate (stop 58).

The stack runs :meth:`InverterPlant.evaluate` itself, with each parameter an
array over the rows where the plants differ. Elementwise arithmetic on such an
array gives each row the same bits as its own plant would. An effect that some
plants lack is given to all of them, at its ``neutral`` values (see
:mod:`.effects`) for those without it; a delay is padded to the longest Padé
order with inert states.
"""
from __future__ import annotations

import types
from typing import Sequence

import numpy as np

from .effects import EFFECTS
from .model import N_MEASURED, InverterPlant


# effects InverterPlant.__init__ folds into the circuit, the controller's gains or the delay's state space
_NOT_IN_EVALUATE = ("param_drift", "gain_mismatch", "delay")


def _per_row(values: list, rows: np.ndarray):
    """One value per row, or the plain value where every plant has the same one (no array: same speed)."""
    if all(v == values[0] for v in values[1:]):
        return values[0]
    return np.repeat(np.asarray(values, dtype=float), rows)


class PlantStack(InverterPlant):
    """Plants stacked row-wise: ``rows[i]`` consecutive rows of each batch run ``plants[i]``.

    Parameters
    ----------
    plants : sequence of InverterPlant
    rows : sequence of int
        Number of batch rows (trajectories) each plant runs.

    Only the vector field and :meth:`full_state` are meant for a stack: it has no single
    equilibrium or Jacobian.
    """

    def __init__(self, plants: Sequence[InverterPlant], rows: Sequence[int]):
        if len(plants) != len(rows) or not plants:
            raise ValueError(f"{len(plants)} plants for {len(rows)} row counts")
        self.plants = list(plants)
        self.rows = np.asarray(rows, dtype=int)
        self.n_rows = int(self.rows.sum())
        self.params = plants[0].params
        control = {key: _per_row([getattr(p.control, key) for p in plants], self.rows)
                   for key in plants[0].control.to_dict()}
        self.control = types.SimpleNamespace(**control)
        self.circuit = {key: _per_row([p.circuit[key] for p in plants], self.rows) for key in plants[0].circuit}
        for plant in plants:
            for name in plant.effects:
                if EFFECTS[name].neutral is None and name not in _NOT_IN_EVALUATE:
                    raise ValueError(f"effect {name} has no neutral values: plants with it cannot be stacked")
        names = [name for name in EFFECTS
                 if any(name in p.effects for p in plants) and EFFECTS[name].neutral is not None]
        self.effects = {name: {key: _per_row([p.effects.get(name, EFFECTS[name].neutral)[key] for p in plants],
                                             self.rows)
                               for key in EFFECTS[name].neutral}
                        for name in names}
        self.orders = [0 if p._delay is None else p._delay[1].shape[-1] for p in plants]
        order = max(self.orders)
        self._delay = self._stack_delays(order) if order else None
        self.hidden_state_names = tuple(f"delay_d{k}" for k in range(order)) + tuple(
            f"delay_q{k}" for k in range(order))
        self.n_states = N_MEASURED + 2 * order

    def _stack_delays(self, order: int):
        """Each row's Padé state space, padded to ``order`` with inert states (z' = −z, no output)."""
        a = np.repeat(-np.eye(order)[None], len(self.plants), axis=0)
        b = np.zeros((len(self.plants), order))
        c = np.zeros((len(self.plants), order))
        d = np.ones(len(self.plants))  # a plant without a delay passes its command through
        for i, plant in enumerate(self.plants):
            if plant._delay is not None:
                ai, bi, ci, di = plant._delay
                n = bi.shape[-1]
                a[i, :n, :n], b[i, :n], c[i, :n], d[i] = ai, bi, ci, di
        return tuple(np.repeat(m, self.rows, axis=0) for m in (a, b, c, d))

    def full_state(self, x_measured, u) -> np.ndarray:
        """Each plant's own hidden states for its rows (see :meth:`InverterPlant.full_state`), padded."""
        x_measured = np.asarray(x_measured, dtype=float)
        if x_measured.shape[0] != self.n_rows:
            raise ValueError(f"{x_measured.shape[0]} rows of states for a stack of {self.n_rows} rows")
        u = np.asarray(u, dtype=float)
        order = (self.n_states - N_MEASURED) // 2
        full = np.zeros((self.n_rows, self.n_states))
        first = 0
        for plant, count, own in zip(self.plants, self.rows, self.orders):
            rows = slice(first, first + count)
            state = plant.full_state(x_measured[rows], u[rows])
            full[rows, :N_MEASURED] = state[:, :N_MEASURED]
            full[rows, N_MEASURED:N_MEASURED + own] = state[:, N_MEASURED:N_MEASURED + own]
            full[rows, N_MEASURED + order:N_MEASURED + order + own] = state[:, N_MEASURED + own:]
            first += count
        return full

    def equilibrium(self, *args, **kwargs):
        raise NotImplementedError("a stack of plants has no single equilibrium; ask each plant")

    def jacobian(self, *args, **kwargs):
        raise NotImplementedError("a stack of plants has no single Jacobian; ask each plant")
