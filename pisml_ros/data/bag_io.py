"""rosbag2 datasets (mcap by default), written and read with ``rosbags`` (no ROS install needed).

A dataset travels as ``pisml_msgs/msg/MeasurementBatch`` messages on the
measurement topic (~100 samples per message), plus one ``std_msgs/msg/String``
on :data:`INFO_TOPIC` carrying the dataset metadata as JSON. Bags written here
play in ``ros2 bag`` on a real install; bags recorded there from the live
measurement topic read here.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import sys
from pathlib import Path

import numpy as np

from ..fileio import json_default
from .dataset import Dataset, DataError, Trajectory, check_sampling

MEASUREMENT_TOPIC = "/pisml/measurement"
INFO_TOPIC = "/pisml/dataset_info"
BATCH_TYPE = "pisml_msgs/msg/MeasurementBatch"
STRING_TYPE = "std_msgs/msg/String"
DEFAULT_BATCH_SIZE = 100
_MSG_FILE = "MeasurementBatch.msg"


def find_msg_definition(name: str = _MSG_FILE) -> Path:
    """Path of a pisml_msgs .msg file: the source tree first, then installed prefixes."""
    candidates = [Path(__file__).resolve().parents[2] / "msg_defs" / "msg" / name]
    prefixes = [sys.prefix] + [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    candidates += [Path(prefix) / "share" / "pisml_msgs" / "msg" / name for prefix in prefixes]
    for path in candidates:
        if path.is_file():
            return path
    raise DataError(f"cannot find the pisml_msgs definition {name} (looked in {[str(c) for c in candidates]})")


def typestore():
    """A rosbags Kilted type store with pisml_msgs/MeasurementBatch registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_KILTED)
    store.register(get_types_from_msg(find_msg_definition().read_text(), BATCH_TYPE))
    return store


def dataset_to_batches(dataset: Dataset, batch_size: int = DEFAULT_BATCH_SIZE):
    """Yield ``(trajectory, first_index, stop_index, is_last)`` slices of a dataset, in order."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    for traj in dataset.trajectories:
        n = len(traj)
        for start in range(0, n, batch_size):
            stop = min(start + batch_size, n)
            yield traj, start, stop, stop == n


def write_bag(dataset: Dataset, path: str | Path, batch_size: int = DEFAULT_BATCH_SIZE,
              topic: str = MEASUREMENT_TOPIC, storage: str = "mcap", overwrite: bool = True) -> Path:
    """Write a dataset to a rosbag2 directory.

    Parameters
    ----------
    dataset : Dataset
    path : str or Path
        Bag directory (created; must not exist unless ``overwrite``).
    batch_size : int
        Samples per MeasurementBatch message.
    topic : str
    storage : {"mcap", "sqlite3"}

    Returns
    -------
    Path
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = Path(path)
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}.get(storage)
    if plugin is None:
        raise DataError(f"unknown bag storage {storage!r}; use mcap or sqlite3")
    # write beside the target and rename: a crash never leaves a half-written bag at `path`
    staging = path.parent / f".{path.name}.partial"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    tmp = staging / path.name  # same name, so rosbags names the storage file as it would at `path`
    store = typestore()
    batch_cls = store.types[BATCH_TYPE]
    header_cls = store.types["std_msgs/msg/Header"]
    time_cls = store.types["builtin_interfaces/msg/Time"]
    string_cls = store.types[STRING_TYPE]
    dt = dataset.dt
    meta = dict(dataset.metadata, dt=dt, state_names=list(dataset.state_names),
                input_names=list(dataset.input_names))
    with Writer(tmp, version=9, storage_plugin=plugin) as writer:
        info_conn = writer.add_connection(INFO_TOPIC, STRING_TYPE, typestore=store)
        conn = writer.add_connection(topic, BATCH_TYPE, typestore=store)
        # log times: trajectories laid end to end, 1 s apart, starting at t = 1 s
        offset = 1.0
        writer.write(info_conn, int(offset * 1e9) - 1,
                     store.serialize_cdr(string_cls(data=json.dumps(meta, default=json_default)), STRING_TYPE))
        for traj, start, stop, last in dataset_to_batches(dataset, batch_size):
            if start == 0 and traj is not dataset.trajectories[0]:
                offset += 1.0
            t0 = float(traj.t[start])
            stamp = offset + t0
            sec = int(math.floor(stamp))
            msg = batch_cls(
                header=header_cls(stamp=time_cls(sec=sec, nanosec=int(round((stamp - sec) * 1e9)) % 1_000_000_000),
                                  frame_id="pisml"),
                trajectory_id=int(traj.traj_id),
                first_sample_index=int(start),
                t0=t0,
                dt=float(dt),
                end_of_trajectory=bool(last),
                state_names=list(dataset.state_names),
                input_names=list(dataset.input_names),
                x=np.ascontiguousarray(traj.x[start:stop]).ravel(),
                u=np.ascontiguousarray(traj.u[start:stop]).ravel(),
            )
            writer.write(conn, int(round(stamp * 1e9)), store.serialize_cdr(msg, BATCH_TYPE))
    if path.exists():
        if not overwrite:
            shutil.rmtree(staging, ignore_errors=True)
            raise DataError(f"{path}: exists (refusing to overwrite)")
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    tmp.rename(path)
    staging.rmdir()
    return path


def read_bag(path: str | Path, topic: str | None = None, sampling_rtol: float = 0.01) -> Dataset:
    """Read a rosbag2 directory of MeasurementBatch messages into a Dataset.

    Batches are grouped by trajectory id and ordered by their first sample
    index (the order in the bag does not matter); the names, dt and lengths of
    every batch are checked.

    Raises
    ------
    DataError
        Naming the bag, the message (by index and trajectory) and the field:
        not a bag, no measurement topic, inconsistent names or dt, wrong x/u
        lengths, NaN/inf, missing or overlapping samples.
    """
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not (path / "metadata.yaml").is_file():
        raise DataError(f"{path}: not a rosbag2 directory (no metadata.yaml)")
    store = typestore()
    try:
        reader = Reader(path)
        reader.open()
    except Exception as err:  # rosbags raises several types for corrupt bags
        raise DataError(f"{path}: cannot open bag: {err}") from None
    try:
        conns = [c for c in reader.connections if c.msgtype == BATCH_TYPE and (topic is None or c.topic == topic)]
        if not conns:
            found = sorted({f"{c.topic} [{c.msgtype}]" for c in reader.connections})
            raise DataError(f"{path}: no {BATCH_TYPE} messages"
                            f"{' on ' + topic if topic else ''} (topics: {found})")
        info_conns = [c for c in reader.connections if c.topic == INFO_TOPIC and c.msgtype == STRING_TYPE]
        meta = {}
        # (an empty connection list would mean "all messages" to rosbags)
        for _, _, raw in reader.messages(connections=info_conns) if info_conns else ():
            try:
                meta = json.loads(store.deserialize_cdr(raw, STRING_TYPE).data)
            except Exception:  # metadata is optional: a bad one is ignored, the data still reads
                meta = {}
        batches = {}
        names = None
        dt = None
        for index, (_, _, raw) in enumerate(reader.messages(connections=conns)):
            where = f"{path}: message {index}"
            try:
                msg = store.deserialize_cdr(raw, BATCH_TYPE)
            except Exception as err:
                raise DataError(f"{where}: cannot decode {BATCH_TYPE}: {err}") from None
            check = validate_batch(msg, where)
            if names is None:
                names, dt = (check["state_names"], check["input_names"]), check["dt"]
            elif (check["state_names"], check["input_names"]) != names:
                raise DataError(f"{where} (trajectory {msg.trajectory_id}): field state_names/input_names "
                                f"differ from the first batch")
            elif abs(check["dt"] - dt) > 1e-9 * dt:
                raise DataError(f"{where} (trajectory {msg.trajectory_id}): field dt={check['dt']!r} differs "
                                f"from the first batch ({dt!r})")
            batches.setdefault(int(msg.trajectory_id), []).append((int(msg.first_sample_index), msg.t0, check))
    finally:
        reader.close()
    trajectories = []
    for tid, items in batches.items():
        items.sort(key=lambda item: item[0])
        expected = items[0][0]
        if expected != 0:
            raise DataError(f"{path}: trajectory {tid}: first batch starts at sample {expected}, not 0 "
                            f"(samples 0..{expected - 1} missing)")
        ts, xs, us = [], [], []
        for first, t0, check in items:
            if first != expected:
                kind = "missing" if first > expected else "overlapping"
                raise DataError(f"{path}: trajectory {tid}: {kind} samples at index {min(first, expected)}"
                                f"..{max(first, expected) - 1}")
            n = check["x"].shape[0]
            ts.append(t0 + np.arange(n) * dt)
            xs.append(check["x"])
            us.append(check["u"])
            expected = first + n
        traj = Trajectory(tid, np.concatenate(ts), np.concatenate(xs), np.concatenate(us))
        check_sampling(traj, dt, str(path), sampling_rtol)
        trajectories.append(traj)
    meta = dict(meta)
    meta.update(dt=dt, state_names=list(names[0]), input_names=list(names[1]))
    meta.setdefault("source", str(path))
    return Dataset(names[0], names[1], trajectories, meta)


def validate_batch(msg, where: str = "batch") -> dict:
    """Check one MeasurementBatch (any object with its fields) and return its arrays.

    Returns ``{"state_names", "input_names", "dt", "x" (n, n_states), "u" (n, n_inputs)}``.

    Raises
    ------
    DataError
        Naming the field: empty or duplicate names, non-positive or non-finite
        dt or t0, x/u lengths that disagree with the names, NaN/inf values.
    """
    tid = getattr(msg, "trajectory_id", "?")
    where = f"{where} (trajectory {tid})"
    states = tuple(str(s) for s in msg.state_names)
    inputs = tuple(str(s) for s in msg.input_names)
    if not states:
        raise DataError(f"{where}: field state_names is empty")
    if len(set(states + inputs)) != len(states + inputs):
        raise DataError(f"{where}: fields state_names/input_names contain duplicates")
    dt = float(msg.dt)
    if not math.isfinite(dt) or dt <= 0:
        raise DataError(f"{where}: field dt must be a positive number, got {dt!r}")
    if not math.isfinite(float(msg.t0)):
        raise DataError(f"{where}: field t0 is not finite ({msg.t0!r})")
    x = np.asarray(msg.x, dtype=float)
    u = np.asarray(msg.u, dtype=float)
    if x.size == 0 or x.size % len(states):
        raise DataError(f"{where}: field x has {x.size} values, not a positive multiple of "
                        f"{len(states)} states")
    n = x.size // len(states)
    if u.size != n * len(inputs):
        raise DataError(f"{where}: field u has {u.size} values, expected {n} samples x {len(inputs)} inputs "
                        f"= {n * len(inputs)}")
    x = x.reshape(n, len(states))
    u = u.reshape(n, len(inputs))
    for field, arr, names in (("x", x, states), ("u", u, inputs)):
        bad = np.argwhere(~np.isfinite(arr))
        if bad.size:
            r, c = bad[0]
            raise DataError(f"{where}: field {field}, sample {r}, signal {names[c]}: value {arr[r, c]} "
                            f"(NaN/inf not allowed)")
    return {"state_names": states, "input_names": inputs, "dt": dt, "x": x, "u": u}
