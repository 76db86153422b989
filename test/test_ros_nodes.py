"""Topic-level integration tests: real node processes over loopback DDS, asserted on what arrives."""
import time

import numpy as np
import pytest

from pisml_ros.data import read_csv, write_csv
from pisml_ros.plant import InverterPlant
from pisml_ros.plant.scenarios import generate, schedules_for

from ros_helpers import diagnostic_values, probe_node, spin_until, start_node, stop_all, stop_node

rclpy = pytest.importorskip("rclpy")
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from pisml_msgs.msg import MeasurementBatch, StabilityReport  # noqa: E402

from pisml_ros.ros.common import latched_qos, measurement_qos  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]


@pytest.fixture(scope="module")
def probe():
    yield from probe_node("pisml_test_probe")


def test_analyser_publishes_latched_plant_stability(probe, tmp_path):
    proc = start_node("pisml-analyser", "-p", "analyse_plant:=true", "-p", "ug_points:=[0.8, 1.2]",
                      log_dir=tmp_path)
    try:
        time.sleep(2.0)  # subscribe late on purpose: the reports are transient-local
        reports = []
        sub = probe.create_subscription(StabilityReport, "/pisml/stability", reports.append, latched_qos(10))
        # the depth holds every operating point: a late subscriber gets both reports, in order
        assert spin_until(probe, lambda: len(reports) == 2, 20.0), proc.log_path.read_text()
        assert [list(r.input_values) for r in reports] == [[0.8, 0.0], [1.2, 0.0]]
        assert reports[0].stable is True and reports[0].message == "stable"
        report = reports[-1]
        assert report.model_id == "plant" and list(report.input_values) == [1.2, 0.0]
        assert report.stable is False and report.max_real_part == pytest.approx(0.255, abs=1e-3)
        eig = np.array(report.eigenvalues_real) + 1j * np.array(report.eigenvalues_imag)
        truth = InverterPlant().eigenvalues(1.2)
        assert np.allclose(np.sort_complex(eig), np.sort_complex(truth), rtol=1e-9, atol=1e-9)
        assert report.ug_margin == pytest.approx(1.2 - 1.1661, abs=1e-3)
        assert len(report.modes) == 13 and report.modes[0].dominant_states
        probe.destroy_subscription(sub)
    finally:
        assert stop_node(proc) == 0


def test_analyser_reports_the_model_inside_a_microgrid(probe, tmp_path):
    import json
    from pathlib import Path

    from std_msgs.msg import String

    config = Path(__file__).resolve().parents[1] / "config" / "microgrid.yaml"
    proc = start_node("pisml-analyser", "-p", "analyse_plant:=true", "-p", f"microgrid_config:={config}",
                      "-p", "sweep_points:=0", log_dir=tmp_path)
    try:
        got = []
        sub = probe.create_subscription(String, "/pisml/microgrid", got.append, latched_qos())
        assert spin_until(probe, lambda: got, 30.0), proc.log_path.read_text()
        report = json.loads(got[0].data)
        assert report["model_id"] == "plant" and report["unit"] == "target" and report["stable"] is True
        assert [u["name"] for u in report["units"]] == ["target", "aux1", "aux2"]
        assert report["max_real"] == pytest.approx(-1.532, abs=1e-3)  # as `pisml microgrid` on the same file
        assert report["weakest_modes"][0]["unit_shares"]["target"] > 0.9
        probe.destroy_subscription(sub)
    finally:
        assert stop_node(proc) == 0
    (tmp_path / "bad").mkdir()
    bad = start_node("pisml-analyser", "-p", f"microgrid_config:={config}", "-p", "microgrid_unit:=nobody",
                     log_dir=tmp_path / "bad")
    assert bad.wait(timeout=60) != 0  # refused at start-up, with the entry named
    assert "microgrid_unit: 'nobody' is not a unit" in bad.log_path.read_text()


def test_looped_playback_keeps_real_time_across_passes(probe, tmp_path):
    # a pass of 10 ms: each restart of the loop must continue the time base, or a late timer tick
    # at every wrap (~2 ms) would cost a fifth of the samples
    data = generate(InverterPlant(), *schedules_for("train", seed=4, n_traj=1, duration=0.01))
    csv_path = write_csv(data, tmp_path / "short.csv")
    arrivals = []
    sub = probe.create_subscription(MeasurementBatch, "/pisml/measurement",
                                    lambda msg: arrivals.append((time.monotonic(), len(msg.x) // 13)),
                                    measurement_qos())
    meas = start_node("pisml-measurement", "-p", "source:=csv", "-p", f"path:={csv_path}", "-p", "rate:=1.0",
                      "-p", "loop:=true", "-p", "batch_size:=50", "-p", "start_delay:=0.0", log_dir=tmp_path)
    try:
        assert spin_until(probe, lambda: arrivals and arrivals[-1][0] - arrivals[0][0] > 4.0, 30.0), \
            meas.log_path.read_text()
        t_first = arrivals[0][0] + 1.0  # past discovery and the first catch-up
        window = [(t, n) for t, n in arrivals if t >= t_first]
        rate = sum(n for _, n in window[1:]) / (window[-1][0] - window[0][0])
        assert rate == pytest.approx(10_000, rel=0.03)
    finally:
        probe.destroy_subscription(sub)
        assert stop_node(meas) == 0


def test_measurement_to_identifier_carries_every_sample(probe, tmp_path):
    schedules, _ = schedules_for("train", seed=4, n_traj=3)
    data = generate(InverterPlant(), schedules, 0.02)
    csv_path = write_csv(data, tmp_path / "data.csv")
    batches, diags = [], []
    subs = [probe.create_subscription(MeasurementBatch, "/pisml/measurement", batches.append, measurement_qos()),
            probe.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 50)]
    ident = start_node("pisml-identifier", log_dir=tmp_path)
    meas = start_node("pisml-measurement", "-p", "source:=csv", "-p", f"path:={csv_path}", "-p", "rate:=0.0",
                      "-p", "wait_for_subscribers:=2", "-p", "start_delay:=0.5", "-p", "batch_size:=50",
                      log_dir=tmp_path)
    try:
        def identifier_has_all():
            _, values = diagnostic_values(diags, "pisml: identifier")
            return values.get("complete_trajectories") == "3"

        assert spin_until(probe, identifier_has_all, 40.0), ident.log_path.read_text() + meas.log_path.read_text()
        _, values = diagnostic_values(diags, "pisml: identifier")
        assert values["buffered_samples"] == str(data.n_samples) and values["rejected_batches"] == "0"
        # what travelled on the topic is the file, sample for sample
        got = {}
        for msg in batches:
            got.setdefault(msg.trajectory_id, []).append((msg.first_sample_index, np.array(msg.x)))
        assert sorted(got) == [0, 1, 2]
        for tr in read_csv(csv_path):
            parts = [x for _, x in sorted(got[tr.traj_id], key=lambda p: p[0])]
            assert np.array_equal(np.concatenate(parts).reshape(-1, 13), tr.x)
    finally:
        for sub in subs:
            probe.destroy_subscription(sub)
        assert stop_all(meas, ident) == [0, 0]


def test_identifier_rejects_malformed_batches_and_keeps_running(probe, tmp_path):
    ident = start_node("pisml-identifier", log_dir=tmp_path)
    diags = []
    sub = probe.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 50)
    pub = probe.create_publisher(MeasurementBatch, "/pisml/measurement", measurement_qos())
    try:
        # the identifier is the only subscriber of the measurement topic here
        assert spin_until(probe, lambda: pub.get_subscription_count() > 0, 20.0)

        def batch(**fields):
            msg = MeasurementBatch(trajectory_id=0, first_sample_index=0, t0=0.0, dt=1e-4, end_of_trajectory=True,
                                   state_names=["a", "b"], input_names=["ug"], x=[0.0] * 4, u=[1.0] * 2)
            for key, value in fields.items():
                setattr(msg, key, value)
            return msg

        bad = [batch(x=[0.0] * 5), batch(x=[0.0, float("nan"), 0.0, 0.0]), batch(dt=0.0),
               batch(state_names=["a", "a"])]
        for msg in bad:
            pub.publish(msg)

        def rejected(n):
            return lambda: diagnostic_values(diags, "pisml: identifier")[1].get("rejected_batches") == str(n)

        assert spin_until(probe, rejected(4), 20.0), ident.log_path.read_text()
        status, values = diagnostic_values(diags, "pisml: identifier")
        assert status.level == status.WARN and "field" in values["last_error"]
        # wrong dt for the buffer / unknown names after a good batch
        pub.publish(batch())
        pub.publish(batch(trajectory_id=1, dt=2e-4))
        pub.publish(batch(trajectory_id=2, state_names=["a", "zz"]))
        assert spin_until(probe, rejected(6), 20.0)
        assert spin_until(probe, lambda: diagnostic_values(diags, "pisml: identifier")[1].get(
            "complete_trajectories") == "1", 10.0)
        assert ident.poll() is None  # still running
    finally:
        probe.destroy_subscription(sub)
        probe.destroy_publisher(pub)
        assert stop_node(ident) == 0


def test_nodes_take_a_params_file_and_stop_cleanly(tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text("measurement:\n  ros__parameters:\n    source: sim\n    scenario: test\n    rate: 0.0\n"
                      "    exit_when_done: true\n    start_delay: 0.0\n    wait_for_subscribers: 0\n")
    proc = start_node("pisml-measurement", "--params-file", str(params), log_dir=tmp_path)
    assert proc.wait(60) == 0, proc.log_path.read_text()  # exit_when_done from the file
    assert "2 trajectories, 802 samples" in proc.log_path.read_text()
    bad = start_node("pisml-measurement", "-p", "source:=csv", "-p", f"path:={tmp_path / 'missing.csv'}",
                     log_dir=tmp_path)
    assert bad.wait(60) == 2
    assert "missing.csv" in bad.log_path.read_text() and "Traceback" not in bad.log_path.read_text()


def test_gap_node_publishes_a_gap_report(probe, tmp_path):
    from pisml_msgs.msg import GapReport

    schedules, duration = schedules_for("test")
    data = generate(InverterPlant(effects={"current_limit": {"imax": 1.5}}), schedules, duration)
    csv_path = write_csv(data, tmp_path / "limited.csv")
    reports = []
    sub = probe.create_subscription(GapReport, "/pisml/gap", reports.append, latched_qos())
    gap = start_node("pisml-gap", "-p", "min_trajectories:=2", log_dir=tmp_path)
    meas = start_node("pisml-measurement", "-p", "source:=csv", "-p", f"path:={csv_path}", "-p", "rate:=0.0",
                      "-p", "wait_for_subscribers:=1", log_dir=tmp_path)
    try:
        assert spin_until(probe, lambda: reports, 240.0), gap.log_path.read_text()
        msg = reports[-1]
        assert msg.effect_missing and msg.effects[0].name == "current_limit"
        imax = dict(zip(msg.effects[0].param_names, msg.effects[0].param_values))["imax"]
        assert imax == pytest.approx(1.5, rel=0.05)
        assert msg.gap_after < msg.gap_before / 10 and msg.windows
    finally:
        probe.destroy_subscription(sub)
        assert stop_all(meas, gap) == [0, 0]
