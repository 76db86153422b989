"""Assemble streamed measurement batches into trajectories (used by the identifier node).

Handles out-of-order batches (held until the gap fills), duplicates and
overlaps (rejected), restarts (a batch at sample 0 of a finished trajectory id
begins a new trajectory) and inconsistent names or sample periods (rejected).
"""
from __future__ import annotations

import numpy as np

from .dataset import Dataset, DataError, Trajectory


class _Open:
    def __init__(self, traj_id: int):
        self.traj_id = traj_id
        self.parts: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.next_index = 0
        self.pending: dict[int, tuple[float, dict, bool]] = {}
        self.ended = False


class TrajectoryBuffer:
    """Buffer of trajectories built from batches.

    Parameters
    ----------
    max_samples : int
        Oldest complete trajectories are dropped beyond this many samples.
    """

    def __init__(self, max_samples: int = 2_000_000):
        self.max_samples = max_samples
        self.state_names: tuple | None = None
        self.input_names: tuple | None = None
        self.dt: float | None = None
        self.complete: list[Trajectory] = []
        self.open: dict[int, _Open] = {}
        self.next_uid = 0
        self.dropped = 0
        self.restarts = 0

    def add(self, traj_id: int, first_index: int, t0: float, arrays: dict, end: bool) -> str:
        """Add one validated batch (see :func:`pisml_ros.data.validate_batch`).

        Returns
        -------
        str
            A short event description ("trajectory 3 complete: 401 samples") or "".

        Raises
        ------
        DataError
            Names or dt inconsistent with earlier batches; duplicate or overlapping samples.
        """
        names = (arrays["state_names"], arrays["input_names"])
        if self.state_names is None:
            self.state_names, self.input_names, self.dt = names[0], names[1], arrays["dt"]
        elif names != (self.state_names, self.input_names):
            raise DataError(f"trajectory {traj_id}: signal names {list(names[0] + names[1])} differ from the "
                            f"buffer's {list(self.state_names + self.input_names)}")
        elif abs(arrays["dt"] - self.dt) > 1e-9 * self.dt:
            raise DataError(f"trajectory {traj_id}: dt={arrays['dt']!r} differs from the buffer's dt={self.dt!r}")
        event = ""
        current = self.open.get(traj_id)
        if current is None or (current.ended and first_index == 0):
            if current is not None:
                self.restarts += 1
            current = self.open[traj_id] = _Open(traj_id)
        if first_index < current.next_index or first_index in current.pending:
            raise DataError(f"trajectory {traj_id}: batch at sample {first_index} duplicates or overlaps samples "
                            f"already received (next expected {current.next_index})")
        current.pending[first_index] = (t0, arrays, end)
        while current.next_index in current.pending:
            t0_, arr, end_ = current.pending.pop(current.next_index)
            current.parts.append((t0_, arr["x"], arr["u"]))
            current.next_index += arr["x"].shape[0]
            if end_:
                current.ended = True
        if current.ended and not current.pending:
            traj = self._close(current)
            event = f"trajectory {traj_id} complete: {len(traj)} samples"
        return event

    def _close(self, current: _Open) -> Trajectory:
        x = np.concatenate([x for _, x, _ in current.parts])
        # the parts are contiguous in sample index: one grid from the first t0, as the recorder's
        # own k·dt (per-batch t0 + j·dt differs from it in the last bit at every batch boundary)
        t = current.parts[0][0] + np.arange(x.shape[0]) * self.dt
        u = np.concatenate([u for _, _, u in current.parts])
        traj = Trajectory(self.next_uid, t, x, u)
        self.next_uid += 1
        self.complete.append(traj)
        current.parts, current.ended = [], True
        while sum(len(tr) for tr in self.complete) > self.max_samples and len(self.complete) > 1:
            self.complete.pop(0)
            self.dropped += 1
        return traj

    def gaps(self) -> list[str]:
        """Descriptions of open trajectories waiting for missing samples."""
        out = []
        for tid, cur in self.open.items():
            if cur.pending:
                first = min(cur.pending)
                out.append(f"trajectory {tid}: samples {cur.next_index}..{first - 1} missing")
        return out

    def stats(self) -> dict:
        return {
            "complete_trajectories": len(self.complete),
            "buffered_samples": sum(len(tr) for tr in self.complete),
            "open_trajectories": sum(1 for cur in self.open.values() if not cur.ended or cur.pending),
            "gaps": len(self.gaps()),
            "restarts": self.restarts,
            "dropped_trajectories": self.dropped,
        }

    def dataset(self) -> Dataset:
        """The complete trajectories as a Dataset."""
        if self.state_names is None:
            raise DataError("no measurements received yet")
        return Dataset(self.state_names, self.input_names, list(self.complete), {"dt": self.dt, "source": "stream"})
