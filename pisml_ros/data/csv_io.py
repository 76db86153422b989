"""CSV datasets (contract): header ``traj,t,<states...>,<inputs...>``, one row per sample.

An optional JSON sidecar with the same stem (``name.json`` beside ``name.csv``)
carries the metadata: sample period, signal names, units, parameters, provenance.
"""
from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from ..signals import INPUT_NAMES
from ..fileio import atomic_write_text, json_default
from .dataset import Dataset, DataError, Trajectory, check_sampling


def sidecar_path(path: str | Path) -> Path:
    return Path(path).with_suffix(".json")


def write_csv(dataset: Dataset, path: str | Path, sidecar: bool = True) -> Path:
    """Write a dataset as contract CSV (17 significant digits: lossless) plus its JSON sidecar."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = ["traj", "t", *dataset.state_names, *dataset.input_names]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as fh:
        fh.write(",".join(header) + "\n")
        for traj in dataset.trajectories:
            block = np.column_stack([traj.t, traj.x, traj.u])
            prefix = f"{int(traj.traj_id)},"
            buf = io.StringIO()
            np.savetxt(buf, block, delimiter=",", fmt="%.17g")
            fh.writelines(prefix + line + "\n" for line in buf.getvalue().splitlines())
    tmp.replace(path)
    if sidecar:
        meta = dict(dataset.metadata)
        meta.setdefault("dt", dataset.dt if dataset.trajectories else None)
        meta["state_names"] = list(dataset.state_names)
        meta["input_names"] = list(dataset.input_names)
        atomic_write_text(sidecar_path(path), json.dumps(meta, indent=2, sort_keys=True, default=json_default) + "\n")
    return path


def read_csv(path: str | Path, input_names=None, expected_states=None, sampling_rtol: float = 0.01) -> Dataset:
    """Read and validate a contract CSV dataset.

    Parameters
    ----------
    path : str or Path
    input_names : sequence of str, optional
        Which columns are inputs. Default: from the sidecar, else ``ug, theta_g``.
    expected_states : sequence of str, optional
        States that must be present (missing ones are an error).
    sampling_rtol : float
        Tolerated deviation of a sample step from the sample period, relative.

    Returns
    -------
    Dataset

    Raises
    ------
    DataError
        Naming file, row (1-based, header = row 1) and column: missing columns,
        non-numeric values, NaN/inf, non-integer traj, non-increasing t,
        irregular sampling.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise DataError(f"{path}: cannot read CSV ({getattr(err, 'strerror', None) or err})") from None
    meta = {}
    side = sidecar_path(path)
    if side.is_file():
        try:
            meta = json.loads(side.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise DataError(f"{side}: sidecar is not valid JSON ({err})") from None
        if not isinstance(meta, dict):
            raise DataError(f"{side}: sidecar must hold a JSON object")
    rows = csv.reader(io.StringIO(text))
    try:
        header = [h.strip() for h in next(rows)]
    except StopIteration:
        raise DataError(f"{path}: empty file (expected header traj,t,<states...>,<inputs...>)") from None
    if header[:2] != ["traj", "t"]:
        missing = [c for c in ("traj", "t") if c not in header]
        raise DataError(f"{path}: row 1: header must start with 'traj,t' "
                        f"({'missing column ' + ', '.join(missing) if missing else 'got ' + ','.join(header[:2])})")
    if len(set(header)) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise DataError(f"{path}: row 1: duplicate column(s) {dup}")
    signals = header[2:]
    inputs = list(input_names if input_names is not None else meta.get("input_names", INPUT_NAMES))
    missing_inputs = [name for name in inputs if name not in signals]
    if missing_inputs:
        raise DataError(f"{path}: missing input column(s) {missing_inputs} (header: {','.join(header)})")
    states = [name for name in signals if name not in inputs]
    expected = list(expected_states if expected_states is not None else meta.get("state_names", []))
    missing_states = [name for name in expected if name not in states]
    if missing_states:
        raise DataError(f"{path}: missing state column(s) {missing_states}")
    if not states:
        raise DataError(f"{path}: no state columns (header: {','.join(header)})")
    if expected:  # keep the documented order where the file permutes it
        states = expected + [s for s in states if s not in expected]

    values = _parse_numbers(path, text, header)
    col = {name: k for k, name in enumerate(header)}
    traj_col = values[:, 0]
    frac = np.flatnonzero(traj_col != np.round(traj_col))
    if frac.size:
        raise DataError(f"{path}: row {frac[0] + 2}, column traj: not an integer: {traj_col[frac[0]]!r}")
    ids = traj_col.astype(np.int64)
    order_ids = list(dict.fromkeys(ids.tolist()))
    trajectories = []
    for tid in order_ids:
        rows_idx = np.flatnonzero(ids == tid)
        if rows_idx.size and np.any(np.diff(rows_idx) != 1):
            gap = rows_idx[np.flatnonzero(np.diff(rows_idx) != 1)[0] + 1]
            raise DataError(f"{path}: row {gap + 2}, column traj: rows of trajectory {tid} are not contiguous")
        block = values[rows_idx]
        traj = Trajectory(int(tid), block[:, 1], block[:, [col[s] for s in states]],
                          block[:, [col[s] for s in inputs]])
        trajectories.append(traj)
    dt = meta.get("dt")
    if dt is None:
        steps = np.concatenate([np.diff(tr.t) for tr in trajectories if len(tr) > 1] or [np.array([])])
        if steps.size == 0:
            raise DataError(f"{path}: cannot tell the sample period (no trajectory with two samples, no sidecar dt)")
        dt = float(np.median(steps))
    try:
        dt = float(dt)
    except (TypeError, ValueError):
        raise DataError(f"{side}: dt is not a number: {dt!r}") from None
    if not math.isfinite(dt) or dt <= 0:
        raise DataError(f"{path}: sample period must be positive, got {dt!r}")
    for traj, tid in zip(trajectories, order_ids):
        try:
            check_sampling(traj, dt, str(path), sampling_rtol)
        except DataError as err:  # add the row number of the offending sample
            first_row = int(np.flatnonzero(ids == tid)[0]) + 2
            sample = _sample_in_message(str(err))
            raise DataError(f"{err} (row {first_row + sample}, column t)") from None
    meta = dict(meta)
    meta["dt"] = dt
    meta["state_names"], meta["input_names"] = list(states), list(inputs)
    meta.setdefault("source", str(path))
    return Dataset(tuple(states), tuple(inputs), trajectories, meta)


def _sample_in_message(message: str) -> int:
    marker = "at sample "
    try:
        return int(message.split(marker, 1)[1].split()[0].rstrip(":"))
    except (IndexError, ValueError):
        return 0


def _parse_numbers(path: Path, text: str, header: list[str]) -> np.ndarray:
    """Parse the body into floats; on failure locate the first bad row and column."""
    n_cols = len(header)
    body = text.split("\n", 1)[1] if "\n" in text else ""
    if not body.strip():
        raise DataError(f"{path}: no data rows")
    try:
        with np.errstate(all="ignore"):
            values = np.loadtxt(io.StringIO(body), delimiter=",", ndmin=2, dtype=float)
        if values.size == 0:
            values = values.reshape(0, n_cols)
        if values.shape[1] != n_cols:
            raise ValueError("column count")
    except ValueError:
        values = None
    if values is None:  # slow pass, only to name the problem
        for row_no, row in enumerate(csv.reader(io.StringIO(body)), start=2):
            if not row or all(not cell.strip() for cell in row):
                continue
            if len(row) != n_cols:
                raise DataError(f"{path}: row {row_no}: {len(row)} values, header has {n_cols} columns")
            for name, cell in zip(header, row):
                try:
                    float(cell)
                except ValueError:
                    raise DataError(f"{path}: row {row_no}, column {name}: not a number: {cell.strip()!r}") from None
        raise DataError(f"{path}: could not parse the numeric body")
    if values.shape[0] == 0:
        raise DataError(f"{path}: no data rows")
    bad = np.argwhere(~np.isfinite(values))
    if bad.size:
        r, c = bad[0]
        raise DataError(f"{path}: row {r + 2}, column {header[c]}: value is {values[r, c]} (NaN/inf not allowed)")
    return values
