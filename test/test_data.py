"""Datasets: CSV and rosbag2 round trips, third-party files, validation of bad input, streaming."""
import csv

import numpy as np
import pytest

from pisml_ros.data import DataError, Dataset, Trajectory, read_bag, read_csv, read_dataset, write_bag, write_csv
from pisml_ros.data.stream import TrajectoryBuffer
from pisml_ros.plant import InverterPlant
from pisml_ros.plant.noise import add_measurement_noise
from pisml_ros.plant.scenarios import generate, schedules_for
from pisml_ros.signals import INPUT_NAMES, STATE_NAMES


@pytest.fixture(scope="module")
def dataset():
    schedules, _ = schedules_for("train", seed=1, n_traj=3)
    return add_measurement_noise(generate(InverterPlant(), schedules, 0.012), 40.0, seed=2)


def _assert_same(a: Dataset, b: Dataset, t_tol=0.0):
    assert a.state_names == b.state_names and a.input_names == b.input_names
    assert [tr.traj_id for tr in a] == [tr.traj_id for tr in b]
    for ta, tb in zip(a, b):
        assert np.array_equal(ta.x, tb.x) and np.array_equal(ta.u, tb.u)
        assert np.allclose(ta.t, tb.t, rtol=0, atol=t_tol) if t_tol else np.array_equal(ta.t, tb.t)


def test_csv_round_trip_is_lossless(tmp_path, dataset):
    path = write_csv(dataset, tmp_path / "d.csv")
    back = read_csv(path)
    _assert_same(dataset, back)
    assert back.metadata["snr_db"] == 40.0 and back.dt == pytest.approx(1e-4)
    header = path.read_text().splitlines()[0]
    assert header == "traj,t," + ",".join(STATE_NAMES + INPUT_NAMES)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_csv_to_bag_to_csv_keeps_values(tmp_path, dataset, storage):
    csv1 = write_csv(dataset, tmp_path / "a.csv")
    bag = write_bag(read_csv(csv1), tmp_path / "bag", storage=storage, batch_size=37)
    from_bag = read_bag(bag)
    _assert_same(dataset, from_bag, t_tol=1e-15)
    csv2 = write_csv(from_bag, tmp_path / "b.csv")
    _assert_same(read_csv(csv1), read_csv(csv2), t_tol=1e-15)
    assert from_bag.metadata["snr_db"] == 40.0
    assert (bag / "metadata.yaml").is_file()


def test_bag_is_written_atomically_and_replaced(tmp_path, dataset):
    bag = write_bag(dataset, tmp_path / "bag")
    write_bag(dataset.select([0]), bag)
    assert len(read_bag(bag)) == 1
    assert not any(p.name.endswith(".partial") for p in tmp_path.iterdir())


def test_third_party_csv_is_accepted(tmp_path):
    # a file written by someone else: few digits, columns permuted, no sidecar
    cols = ["traj", "t", "ug", "theta_g", *reversed(STATE_NAMES)]
    path = tmp_path / "theirs.csv"
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for traj in (3, 7):
            for k in range(50):
                w.writerow([traj, f"{k * 1e-4:.4f}", "0.9", "0.0", *[f"{0.1 * j + k * 1e-3:.6f}" for j in range(13)]])
    ds = read_csv(path)
    assert ds.state_names == STATE_NAMES[::-1] and ds.input_names == INPUT_NAMES
    assert [tr.traj_id for tr in ds] == [3, 7] and ds.dt == pytest.approx(1e-4)
    strict = read_csv(path, expected_states=STATE_NAMES)
    assert strict.state_names == STATE_NAMES
    assert strict.trajectories[0].x[0, 0] == pytest.approx(1.2)  # delta was the last column


GOOD = "traj,t,a,b,ug,theta_g\n0,0,1,2,1,0\n0,0.0001,1,2,1,0\n0,0.0002,1,2,1,0\n"


@pytest.mark.parametrize("text, expected", [
    ("", "empty file"),
    ("t,traj,a,ug,theta_g\n", "header must start with 'traj,t'"),
    ("traj,t,a,b,ug\n0,0,1,2,1\n", r"missing input column\(s\) \['theta_g'\]"),
    (GOOD.replace("0,0.0001,1,2,1,0", "0,0.0001,1,x,1,0"), "row 3, column b: not a number"),
    (GOOD.replace("0,0.0001,1,2,1,0", "0,0.0001,1,nan,1,0"), "row 3, column b: value is nan"),
    (GOOD.replace("0,0.0001,1,2,1,0", "0,0.0001,1,2,inf,0"), "row 3, column ug: value is inf"),
    (GOOD.replace("0,0.0002,", "0,0.00005,"), "row 4, column t"),
    (GOOD + "0,0.0005,1,2,1,0\n", "irregular sampling at sample 3"),
    (GOOD.replace("0,0.0001,1,2,1,0", "0,0.0001,1,2,1"), "row 3: 5 values, header has 6 columns"),
    (GOOD.replace("0,0.0001,", "0.5,0.0001,"), "row 3, column traj: not an integer"),
    ("traj,t,a,b,ug,theta_g\n", "no data rows"),
])
def test_bad_csv_is_rejected_with_file_row_column(tmp_path, text, expected):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(DataError, match=expected) as err:
        read_csv(path)
    assert str(path) in str(err.value)
    assert "\n" not in str(err.value)


def test_missing_expected_state_column(tmp_path):
    path = tmp_path / "d.csv"
    path.write_text(GOOD)
    with pytest.raises(DataError, match=r"missing state column\(s\) \['delta'"):
        read_csv(path, expected_states=STATE_NAMES)


def test_bad_sidecar(tmp_path):
    (tmp_path / "d.csv").write_text(GOOD)
    (tmp_path / "d.json").write_text("{not json")
    with pytest.raises(DataError, match="d.json: sidecar is not valid JSON"):
        read_csv(tmp_path / "d.csv")


def test_bad_bags(tmp_path, dataset):
    with pytest.raises(DataError, match="not a rosbag2 directory"):
        read_bag(tmp_path)
    with pytest.raises(DataError, match="No such file"):
        read_dataset(tmp_path / "missing")
    bag = write_bag(dataset, tmp_path / "bag")
    with pytest.raises(DataError, match="no pisml_msgs/msg/MeasurementBatch messages on /other"):
        read_bag(bag, topic="/other")
    (bag / "metadata.yaml").write_text("garbage: [")
    with pytest.raises(DataError, match="cannot open bag"):
        read_bag(bag)


def _write_raw_batches(path, batches):
    """A bag of hand-made (possibly malformed) batches, written with rosbags directly."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from pisml_ros.data.bag_io import BATCH_TYPE, typestore

    store = typestore()
    cls = store.types[BATCH_TYPE]
    header = store.types["std_msgs/msg/Header"]
    time_ = store.types["builtin_interfaces/msg/Time"]
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/pisml/measurement", BATCH_TYPE, typestore=store)
        for k, fields in enumerate(batches):
            base = dict(header=header(stamp=time_(sec=1, nanosec=k), frame_id=""), trajectory_id=0,
                        first_sample_index=0, t0=0.0, dt=1e-4, end_of_trajectory=True, state_names=["a", "b"],
                        input_names=["ug"], x=np.zeros(4), u=np.zeros(2))
            base.update(fields)
            w.write(conn, 1_000_000_000 + k, store.serialize_cdr(cls(**base), BATCH_TYPE))


@pytest.mark.parametrize("fields, expected", [
    ([{"x": np.zeros(5)}], "message 0 .*field x has 5 values"),
    ([{"u": np.zeros(3)}], "field u has 3 values, expected 2 samples"),
    ([{"x": np.array([0, np.nan, 0, 0.0])}], "field x, sample 0, signal b: value nan"),
    ([{"dt": 0.0}], "field dt must be a positive number"),
    ([{"state_names": ["a", "a"]}], "duplicates"),
    ([{}, {"first_sample_index": 4, "dt": 2e-4}], "message 1 .*field dt"),
    ([{"end_of_trajectory": False}, {"first_sample_index": 5}], "missing samples at index 2..4"),
    ([{"end_of_trajectory": False}, {"first_sample_index": 1}], "overlapping samples"),
])
def test_malformed_batches_in_a_bag(tmp_path, fields, expected):
    _write_raw_batches(tmp_path / "bag", fields)
    with pytest.raises(DataError, match=expected):
        read_bag(tmp_path / "bag")


def test_out_of_order_batches_in_a_bag_are_reassembled(tmp_path):
    x = np.arange(12.0)
    _write_raw_batches(tmp_path / "bag", [
        {"first_sample_index": 2, "t0": 2e-4, "x": x[4:12], "u": np.ones(4)},
        {"first_sample_index": 0, "t0": 0.0, "x": x[0:4], "u": np.ones(2), "end_of_trajectory": False},
    ])
    ds = read_bag(tmp_path / "bag")
    assert np.array_equal(ds.trajectories[0].x.ravel(), x)


def test_noise_has_the_requested_snr(dataset):
    clean_sched, _ = schedules_for("train", seed=1, n_traj=3)
    clean = generate(InverterPlant(), clean_sched, 0.012)
    noisy = add_measurement_noise(clean, 40.0, seed=9)
    x = np.concatenate([tr.x for tr in clean])
    n = np.concatenate([tr.x for tr in noisy]) - x
    snr = 10 * np.log10(np.mean(x ** 2, axis=0) / np.mean(n ** 2, axis=0))
    assert np.all(np.abs(snr - 40.0) < 0.5)
    assert all(np.array_equal(a.u, b.u) for a, b in zip(clean, noisy))


def _arrays(n, names=("a", "b"), inputs=("ug",), dt=1e-4, start=0):
    return {"state_names": names, "input_names": inputs, "dt": dt,
            "x": np.arange(start, start + n * len(names), dtype=float).reshape(n, len(names)),
            "u": np.ones((n, len(inputs)))}


def test_stream_buffer_reorders_rejects_and_restarts():
    buf = TrajectoryBuffer()
    assert buf.add(0, 3, 3e-4, _arrays(2), True) == ""          # early batch held back
    assert buf.gaps() == ["trajectory 0: samples 0..2 missing"]
    assert buf.add(0, 0, 0.0, _arrays(3), False).startswith("trajectory 0 complete: 5")
    with pytest.raises(DataError, match="duplicates or overlaps"):
        buf.add(1, 0, 0.0, _arrays(3), False) or buf.add(1, 2, 2e-4, _arrays(3), False)
    with pytest.raises(DataError, match="signal names"):
        buf.add(2, 0, 0.0, _arrays(3, names=("a", "c")), True)
    with pytest.raises(DataError, match="dt="):
        buf.add(2, 0, 0.0, _arrays(3, dt=2e-4), True)
    buf.add(0, 0, 0.0, _arrays(4), True)  # restart of a finished id: a new trajectory
    ds = buf.dataset()
    assert [len(tr) for tr in ds] == [5, 4] and buf.stats()["restarts"] == 1
    assert np.allclose(ds.trajectories[0].t, np.arange(5) * 1e-4)


def test_dataset_rejects_bad_shapes():
    with pytest.raises(DataError):
        Trajectory(0, np.zeros(3), np.zeros((2, 2)), np.zeros((3, 1)))
    with pytest.raises(DataError):
        Dataset(("a", "t"), ("ug",), [])


def test_steady_start_is_found_with_clean_and_noisy_inputs():
    from pisml_ros.data.dataset import steady_start_length

    rng = np.random.default_rng(0)
    u = np.ones((400, 2)) * [1.0, 0.0]
    u[150:, 0] = 0.9
    clean = Trajectory(0, np.arange(400) * 1e-4, np.zeros((400, 1)), u)
    assert steady_start_length(clean) == 150
    noisy = Trajectory(0, clean.t, clean.x, u + 0.005 * rng.standard_normal(u.shape))
    assert steady_start_length(noisy) == 150
    flat = Trajectory(0, clean.t, clean.x, np.ones((400, 2)))
    assert steady_start_length(flat) == 400


def test_a_steady_start_counts_as_rest_only_where_the_states_sit_still():
    from pisml_ros.data.dataset import rest_start_length, steady_start_mean

    rng = np.random.default_rng(1)
    t = np.arange(400) * 1e-4
    u = np.ones((400, 2)) * [1.0, 0.0]
    u[150:, 0] = 0.9  # inputs constant over the first 150 samples
    at_rest = np.column_stack([np.full(400, 0.5), np.full(400, -0.2)])
    clean = Trajectory(0, t, at_rest, u)
    assert rest_start_length(clean) == 150 and np.allclose(steady_start_mean(clean)[1], [0.5, -0.2])
    noisy = Trajectory(0, t, at_rest + 0.005 * rng.standard_normal(at_rest.shape), u)
    assert rest_start_length(noisy) == 150
    assert np.allclose(steady_start_mean(noisy)[1], [0.5, -0.2], atol=3 * 0.005 / np.sqrt(150) * 2)
    # a record that begins inside a transient (the LCL ring, ~7 samples per period, and a slow
    # drift) has constant inputs too, but it is not at rest: clean or under noise
    ring = 0.05 * np.exp(-t / 0.004) * np.sin(2 * np.pi * 1500 * t)
    drift = 0.01 * (1 - np.exp(-t / 0.02))
    moving = at_rest + np.column_stack([ring, drift])
    for x in (moving, moving + 0.005 * rng.standard_normal(moving.shape)):
        transient = Trajectory(0, t, x, u)
        assert rest_start_length(transient) == 0 and steady_start_mean(transient) == (0, None)
    # too short a steady start to tell
    u_short = u.copy()
    u_short[12:, 0] = 0.9
    assert rest_start_length(Trajectory(0, t, at_rest, u_short)) == 0
