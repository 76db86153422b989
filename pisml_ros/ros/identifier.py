"""identifier node: measurements in, identified models out, stage by stage.

Assembles MeasurementBatch messages into trajectories (gaps, reordering and
restarts handled by :class:`~pisml_ros.data.stream.TrajectoryBuffer`; malformed
batches are rejected with a diagnostic and the node keeps running). Training
runs in a child process (:class:`~pisml_ros.ident.worker.IdentificationWorker`, started warm
ahead of time — the next run's while the current one trains — and closed after its run, so the
node's memory stays flat), watched by a
thread (the executor never blocks): automatically once
``min_trajectories`` complete trajectories are buffered (``retrain_policy``:
``once`` | ``on_new_data`` | ``manual``), or on request through the
``~/identify`` action (data source "buffer" or a CSV/bag path, method,
configuration overrides; feedback per engine update; cancellable).

Every stage's model is published on /pisml/model (transient-local, depth 1):
the sparse backbone first, then the hybrid (backbone + neural residual: no
explicit form, so ``model_json`` is empty), then the best explicit model
before refinement (PISML: as soon as distillation ends), then the final
explicit model, whose metrics include ``final = 1``. Explicit models are saved atomically to
``output_dir`` as ``model_<stage>.json`` and ``latest.json``; the update log and
the engine's training curves go to ``history.json``. ``initial_model`` publishes
a saved model at start-up. /diagnostics carries the buffer, the stage, the
progress, the latest losses and the last error.
"""
from __future__ import annotations

import json
import os
import queue
import threading
import time
from pathlib import Path

from .common import MEASUREMENT_TOPIC, MODEL_TOPIC, declare, latched_qos, measurement_qos, publish_diagnostics, \
    run_node, status

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from pisml_msgs.action import Identify  # noqa: E402
from pisml_msgs.msg import IdentifiedModel, MeasurementBatch  # noqa: E402
from rclpy.action import ActionServer, CancelResponse, GoalResponse  # noqa: E402
from rclpy.callback_groups import ReentrantCallbackGroup  # noqa: E402
from rclpy.node import Node  # noqa: E402

from ..data import DataError, read_dataset, validate_batch  # noqa: E402
from ..data.dataset import records_at_rest  # noqa: E402
from ..data.stream import TrajectoryBuffer  # noqa: E402
from ..fileio import atomic_write_text, json_default  # noqa: E402
from ..ident import IdentConfig, selection_warnings  # noqa: E402
from ..ident.limiter import limit_in_use, limit_note  # noqa: E402
from ..ident.noise import noise_note  # noqa: E402
from ..ident.worker import IdentificationWorker, RunResult  # noqa: E402
from ..model import ExplicitModel  # noqa: E402
from .conversions import model_message, overrides_from_assignments, overrides_from_fields  # noqa: E402

RETRAIN_POLICIES = ("once", "on_new_data", "manual")
STOP_TIMEOUT = 20.0  # s to wait for a running identification to stop when the node shuts down


class Job:
    """One identification run (a child process, watched by a thread of this node)."""

    def __init__(self, run: int, method: str, config: IdentConfig, data, origin: str, goal_handle=None):
        self.run, self.method, self.config, self.data, self.origin = run, method, config, data, origin
        self.model_id = f"{method}-{run}"
        self.goal_handle = goal_handle
        self.stop = threading.Event()
        self.done = threading.Event()
        self.feedback: queue.Queue = queue.Queue()
        self.stage, self.progress, self.epoch, self.losses = "starting", 0.0, 0, {}
        self.result: IdentifiedModel | None = None
        self.metrics: dict = {}
        self.error = ""
        self.cancelled = False
        self.thread: threading.Thread | None = None

    def should_stop(self) -> bool:
        handle = self.goal_handle
        return self.stop.is_set() or (handle is not None and handle.is_cancel_requested)


def _message_stage(engine_stage: str, model) -> str:
    if isinstance(model, ExplicitModel):
        return "backbone" if engine_stage == "backbone" else "explicit"
    return "hybrid"


class IdentifierNode(Node):
    def __init__(self):
        super().__init__("identifier")
        from ..ident import METHODS

        self.min_trajectories = declare(self, "min_trajectories", 12,
                                        "complete trajectories needed before training starts", 1, 10000)
        self.method = declare(self, "method", "pisml", " | ".join(METHODS))
        if self.method not in METHODS:
            raise ValueError(f"parameter method: {self.method!r} is not one of {', '.join(METHODS)}")
        self.retrain_policy = declare(self, "retrain_policy", "once",
                                      "automatic training: once (first time min_trajectories are buffered) | "
                                      "on_new_data (again after retrain_min_new_trajectories more) | manual "
                                      "(only through the ~/identify action)")
        if self.retrain_policy not in RETRAIN_POLICIES:
            raise ValueError(f"parameter retrain_policy: {self.retrain_policy!r} is not one of "
                             f"{', '.join(RETRAIN_POLICIES)}")
        self.retrain_min_new = declare(self, "retrain_min_new_trajectories", 4,
                                       "on_new_data: new complete trajectories that trigger a retraining", 1, 10000)
        # training cost and memory grow with the data: a long-running stream trains on its newest records
        self.max_train = declare(self, "max_train_trajectories", 48,
                                 "automatic training uses at most this many of the newest complete trajectories",
                                 1, 100000)
        self.output_dir = declare(self, "output_dir", "out/identifier",
                                  "where explicit models and history.json are saved, atomically (empty = nowhere)")
        config_file = declare(self, "config_file", "", "identification settings YAML/JSON (empty = defaults)")
        overrides = declare(self, "overrides", [""], "identification settings as KEY=VALUE (over config_file)")
        smallsignal_path = declare(self, "smallsignal_path", "",
                                   "CSV/bag of small-signal records passed to the engine (empty = none)")
        initial_model = declare(self, "initial_model", "", "explicit model JSON published at start-up (empty = none)")
        # 200 000 samples = 20 s at 10 kHz, 500 records of 40 ms: far more than a training run takes, and a
        # bounded, small footprint (~25 MB) for a node that streams for hours
        max_samples = declare(self, "max_buffer_samples", 200_000, "samples kept in the buffer (oldest dropped)",
                              1000, 100_000_000)
        # on a small machine the link must keep a core: training takes the others (torch and BLAS pools)
        self.training_threads = declare(self, "training_threads", max(1, (os.cpu_count() or 2) - 1),
                                        "threads for training (torch and BLAS); leave a core for the link",
                                        1, 256)
        depth = declare(self, "qos_depth", 5000, "depth of the reliable measurement queue", 10, 1000000)
        # configuration errors surface now (exit status 2), not at the first training
        self.base_overrides = overrides_from_assignments(overrides, "parameter overrides")
        self.config_file = config_file
        self.config = IdentConfig.load(config_file or None, self.base_overrides)
        self.smallsignal = read_dataset(_resolve(smallsignal_path, "smallsignal_path")) if smallsignal_path else None

        self.buffer = TrajectoryBuffer(max_samples=max_samples)
        self.lock = threading.RLock()
        self.rejected = 0
        self.last_error = ""
        self.events: list[str] = []
        self.job: Job | None = None
        self.runs = 0
        self.trained_at = None          # buffer.next_uid when the last automatic run started
        self.last_model = ""            # model_id and stage of the last publication
        self.history: list[dict] = []   # engine updates of this node's runs (losses over time)
        self.max_history = 5000
        self._last_diag = 0.0

        # the first run's process is started (and imports the engine, ~2.5 s) now, not when data arrive
        self.worker: IdentificationWorker | None = IdentificationWorker(self.training_threads)
        self.model_pub = self.create_publisher(IdentifiedModel, MODEL_TOPIC, latched_qos())
        self.diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(MeasurementBatch, MEASUREMENT_TOPIC, self._on_batch, measurement_qos(depth))
        self.action = ActionServer(self, Identify, "~/identify", execute_callback=self._execute,
                                   goal_callback=self._on_goal, cancel_callback=lambda _: CancelResponse.ACCEPT,
                                   callback_group=ReentrantCallbackGroup())
        self.create_timer(1.0, self._tick)
        if initial_model:
            model = ExplicitModel.load(initial_model)
            self._publish_model(model, "explicit", f"initial:{Path(initial_model).stem}",
                                {"final": 1.0, "initial": 1.0})
        self.get_logger().info(
            f"listening on {MEASUREMENT_TOPIC}; method {self.method}, retrain_policy {self.retrain_policy}"
            f"{'' if self.retrain_policy == 'manual' else f', training after {self.min_trajectories} trajectories'}"
            + (f"; small-signal data {smallsignal_path} ({len(self.smallsignal)} records)" if self.smallsignal else ""))

    # ------------------------------------------------------------------ measurements
    def _on_batch(self, msg: MeasurementBatch):
        try:
            arrays = validate_batch(msg, where="batch")
            with self.lock:
                event = self.buffer.add(int(msg.trajectory_id), int(msg.first_sample_index), float(msg.t0), arrays,
                                        bool(msg.end_of_trajectory))
        except DataError as err:
            self.rejected += 1
            self.last_error = str(err)
            self.get_logger().warning(f"rejected {err}")
            self._publish_diagnostics()
            return
        if event:
            self.get_logger().info(event)
            self._maybe_train()

    def _running(self) -> bool:
        return self.job is not None and not self.job.done.is_set()

    def _maybe_train(self):
        if self.retrain_policy == "manual":
            return
        with self.lock:
            if self._running() or len(self.buffer.complete) < self.min_trajectories:
                return
            if self.trained_at is not None and (
                    self.retrain_policy == "once" or self.buffer.next_uid - self.trained_at < self.retrain_min_new):
                return
            self.trained_at = self.buffer.next_uid
            data = self.buffer.dataset()
            if len(data) > self.max_train:
                data = data.select([tr.traj_id for tr in data.trajectories[-self.max_train:]])
            self._start_job(self.method, self.config, data, f"buffer ({len(data)} trajectories, automatic)")

    # ------------------------------------------------------------------ the worker
    def _start_job(self, method, config, data, origin, goal_handle=None) -> Job:
        with self.lock:
            self.runs += 1
            job = Job(self.runs, method, config, data, origin, goal_handle)
            self.job = job
        self.get_logger().info(f"run {job.model_id}: training {method} on {origin}, {data.n_samples} samples"
                               f"{', with small-signal data' if self.smallsignal is not None else ''}")
        if not records_at_rest(data):
            self.get_logger().warning(f"run {job.model_id}: none of the {len(data)} training records starts at "
                                      "rest (constant inputs and still states before the first input change)")
        job.thread = threading.Thread(target=self._run_job, args=(job,), daemon=True, name=f"identify-{job.run}")
        job.thread.start()
        return job

    def _take_worker(self) -> IdentificationWorker:
        with self.lock:
            worker, self.worker = self.worker, None
        return worker if worker is not None else IdentificationWorker(self.training_threads)

    def _run_job(self, job: Job):
        started = time.monotonic()
        worker = self._take_worker()
        if not job.stop.is_set():
            with self.lock:
                if self.worker is None:
                    # the next run's process imports the engine (~5 s) while this one trains: a
                    # retraining that starts as this one ends gets its backbone out at once
                    self.worker = IdentificationWorker(self.training_threads)
        result = RunResult("failed", error="no result")
        try:
            worker.submit(job.method, job.config, job.data, self.smallsignal)
            for item in worker.results(should_stop=job.should_stop):
                if isinstance(item, RunResult):
                    result = item
                    break
                if job.stop.is_set():
                    break  # shutting down: the publishers may be gone, the result is not wanted
                self._on_update(job, item, started)
        except Exception as err:  # the job's data could not be sent, ...: reported, never kills the node
            result = RunResult("failed", error=f"{type(err).__name__}: {err}")
        finally:
            worker.close(timeout=5.0 if job.stop.is_set() else 10.0)  # its memory goes back to the OS
        if job.stop.is_set():
            job.done.set()
            return  # the node is shutting down: nothing to publish or start
        if result.status == "done":
            metrics = dict(result.metrics)
            metrics.update(final=1.0, train_trajectories=len(job.data), train_samples=job.data.n_samples,
                           wall_seconds=time.monotonic() - started)
            stage = _message_stage("explicit", result.model)
            job.result = self._publish_model(result.model, stage, job.model_id, metrics)
            job.metrics = metrics
            job.stage, job.progress = "done", 1.0
            self._save_history(result)
            self.get_logger().info(f"run {job.model_id} done in {time.monotonic() - started:.1f} s: {stage} model, "
                                   f"{job.result.n_parameters} parameters")
            noise = noise_note(result.model)
            if noise:
                self.get_logger().info(f"run {job.model_id}: {noise}")
            note = limit_note(result.model)
            if note:
                # a limit the model does without is a caution: its response beyond the records is not the inverter's
                log = self.get_logger().warning if limit_in_use(result.model) is False else self.get_logger().info
                log(f"run {job.model_id}: {note}")
            for warning in selection_warnings(result.model):
                self.get_logger().warning(f"run {job.model_id}: caution: {warning}")
        elif result.status == "cancelled" or (job.should_stop() and result.status == "failed"):
            job.cancelled, job.stage = True, "cancelled"
            self.get_logger().info(f"run {job.model_id}: {result.error or 'cancelled'}")
        else:
            job.error = f"run {job.model_id} failed: {result.error}"
            job.stage = "failed"
            self.last_error = job.error
            self.get_logger().error(job.error)
        job.done.set()
        self._publish_diagnostics()
        self._maybe_train()  # data that arrived meanwhile

    def _on_update(self, job: Job, update, started: float):
        job.stage, job.progress, job.epoch = update.stage, float(update.progress), int(update.epoch)
        job.losses = dict(update.losses)  # numbers only (the worker keeps those)
        del self.history[:-(self.max_history - 1)]  # a node retraining for days keeps its recent curves
        self.history.append({"run": job.model_id, "t": round(time.monotonic() - started, 3),
                             "stage": update.stage, "progress": job.progress, "epoch": job.epoch,
                             "losses": job.losses})
        if job.goal_handle is not None:
            job.feedback.put((update.stage, job.progress, job.epoch, dict(job.losses)))
        if update.model is not None and update.stage != "explicit":  # the final one goes out with all metrics
            stage = _message_stage(update.stage, update.model)
            metrics = dict(job.losses, progress=job.progress, seconds=time.monotonic() - started)
            self._publish_model(update.model, stage, job.model_id, metrics)
            self._save_history(None)
        if time.monotonic() - self._last_diag > 0.5:
            self._publish_diagnostics()

    def _publish_model(self, model, stage: str, model_id: str, metrics: dict) -> IdentifiedModel:
        msg = model_message(model, stage, model_id, metrics, self.get_clock().now().to_msg())
        self.model_pub.publish(msg)
        self.last_model = f"{model_id} ({stage})"
        self.get_logger().info(f"published {self.last_model}: {msg.n_parameters} parameters")
        if self.output_dir and isinstance(model, ExplicitModel):
            try:
                out = Path(self.output_dir)
                model.save(out / f"model_{stage}.json")
                model.save(out / "latest.json")
            except OSError as err:
                self.last_error = f"cannot save the model in {self.output_dir}: {err}"
                self.get_logger().error(self.last_error)
        return msg

    def _save_history(self, result: RunResult | None):
        if not self.output_dir:
            return
        data = {"updates": list(self.history)}
        if result is not None:
            data["training"] = result.history
            data["metrics"] = result.metrics
        try:
            atomic_write_text(Path(self.output_dir) / "history.json", json.dumps(data, default=_json_any) + "\n")
        except OSError as err:
            self.last_error = f"cannot save the history in {self.output_dir}: {err}"

    # ------------------------------------------------------------------ the action
    def _on_goal(self, request):
        if request.source != "buffer" and not request.source:
            self.get_logger().warning("identify goal rejected: empty source")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _execute(self, goal_handle):
        req = goal_handle.request
        result = Identify.Result()
        try:
            method = req.method or self.method
            from ..ident import METHODS

            if method not in METHODS:
                raise ValueError(f"method {method!r} is not one of {', '.join(METHODS)}")
            overrides = dict(self.base_overrides)
            overrides.update(overrides_from_fields(req.override_names, req.override_values, "goal overrides"))
            config = IdentConfig.load(self.config_file or None, overrides)
            if req.source == "buffer":
                with self.lock:
                    if not self.buffer.complete:
                        raise ValueError("source buffer: no complete trajectories received yet")
                    data = self.buffer.dataset()
                origin = f"buffer ({len(data)} trajectories, action)"
            else:
                data = read_dataset(req.source)
                origin = req.source
        except Exception as err:  # bad goals are answered, not raised
            goal_handle.abort()
            result.success, result.message = False, f"rejected: {err}"
            self.get_logger().warning(f"identify goal: {result.message}")
            return result
        # one run at a time: wait for a running one (automatic or another goal)
        while True:
            with self.lock:
                if not self._running():
                    job = self._start_job(method, config, data, origin, goal_handle)
                    break
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
                result.success, result.message = False, "cancelled before it started"
                return result
            goal_handle.publish_feedback(Identify.Feedback(stage="waiting", progress=0.0))
            time.sleep(0.2)
        while True:
            finished = job.done.wait(0.1)
            while True:
                try:
                    stage, progress, epoch, losses = job.feedback.get_nowait()
                except queue.Empty:
                    break
                goal_handle.publish_feedback(Identify.Feedback(
                    stage=stage, progress=progress, epoch=epoch, loss_names=list(losses),
                    loss_values=[float(v) for v in losses.values()]))
            if finished:
                break
        if job.cancelled:
            goal_handle.canceled()
            result.success, result.message = False, f"{job.model_id}: cancelled"
        elif job.error:
            goal_handle.abort()
            result.success, result.message = False, job.error
        else:
            goal_handle.succeed()
            result.success, result.message = True, f"{job.model_id}: {job.result.stage} model"
            result.model = job.result
            result.metric_names = list(job.metrics)
            result.metric_values = [float(v) for v in job.metrics.values()]
        return result

    # ------------------------------------------------------------------ diagnostics
    def _tick(self):
        self._maybe_train()
        self._publish_diagnostics()

    def _publish_diagnostics(self):
        self._last_diag = time.monotonic()
        with self.lock:
            values = dict(self.buffer.stats(), rejected_batches=self.rejected)
            gaps = self.buffer.gaps()
        job = self.job
        if job is None:
            stage = "buffering" if self.retrain_policy != "manual" or not values["complete_trajectories"] else "idle"
            values.update(stage=stage, progress="0")
        else:
            values.update(stage=job.stage, progress=f"{job.progress:.3f}", epoch=job.epoch, run=job.model_id,
                          method=job.method)
            values.update({f"loss.{k}": f"{v:.6g}" for k, v in job.losses.items()})
        values.update(runs=self.runs, last_model=self.last_model, last_error=self.last_error,
                      gap_details="; ".join(gaps))
        level = DiagnosticStatus.WARN if self.last_error else DiagnosticStatus.OK
        message = self.last_error or (f"{values['stage']} {float(values['progress']) * 100:.0f} %"
                                      if job is not None else values["stage"])
        publish_diagnostics(self, self.diagnostics, [status("pisml: identifier", level, message, values)])

    def destroy_node(self):
        job = self.job
        if job is not None and not job.done.is_set():
            job.stop.set()  # the watcher cancels the run and closes its process (terminated if it hangs)
            self.get_logger().info(f"stopping run {job.model_id} ...")
            job.thread.join(STOP_TIMEOUT)
        with self.lock:
            worker, self.worker = self.worker, None
        if worker is not None:
            worker.close(timeout=2.0)
        super().destroy_node()


def _resolve(path: str, parameter: str) -> Path:
    """A relative data path: from the working directory, else from the source tree (bags/ of a checkout)."""
    candidates = [Path(path)]
    if not Path(path).is_absolute():
        candidates.append(Path(__file__).resolve().parents[2] / path)
    for candidate in candidates:
        if candidate.exists():
            return candidate
    raise ValueError(f"parameter {parameter}: {path} not found (looked in {[str(c) for c in candidates]})")


def _json_any(obj):
    try:
        return json_default(obj)
    except TypeError:
        return str(obj)


def main(args=None) -> int:
    return run_node(IdentifierNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
