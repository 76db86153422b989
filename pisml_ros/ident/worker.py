"""Identification in a child process: a long-running caller (the identifier node) keeps flat memory.

A training run peaks at 1–2 GB (torch, dense refinement Jacobians) and an allocator rarely gives
all of it back, so a process that trains again and again grows. :class:`IdentificationWorker`
runs one ``fit`` in a spawned child that has already imported the engine (a warm child is started
ahead of time, so the first stage is not delayed by ~2.5 s of imports; a cold one takes its job
after the backbone's imports and finishes torch's in the background) and exits when the run
ends, returning its memory to the OS. Stage updates and models come back over a pipe as plain
data (:meth:`~pisml_ros.model.ExplicitModel.to_dict`); models without an explicit form come back
as a :class:`ModelSummary`. No rclpy here: usable from any Python program.
"""
from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import os
import signal
import threading
from typing import Iterator

from ..model import ExplicitModel
from .estimators import StageUpdate
from .trajfit import blas_threads


@dataclasses.dataclass
class ModelSummary:
    """What crosses the process boundary of a model with no explicit form (hybrid, neural ODE)."""

    kind: str
    state_names: list
    input_names: list
    n_parameters: int
    backbone: ExplicitModel | None = None


@dataclasses.dataclass
class RunResult:
    """The end of a run: ``status`` done | cancelled | failed, the final model (done), the
    estimator's numeric ``metrics_`` and ``history_``, and ``error`` (failed / cancelled)."""

    status: str
    model: object = None
    metrics: dict = dataclasses.field(default_factory=dict)
    history: dict = dataclasses.field(default_factory=dict)
    error: str = ""


def _pack(model):
    if model is None:
        return None
    if isinstance(model, ExplicitModel):
        return ("explicit", model.to_dict())
    backbone = getattr(model, "backbone", None)
    names_from = backbone if isinstance(backbone, ExplicitModel) else model
    return ("summary", {"kind": str(getattr(model, "kind", type(model).__name__)),
                        "state_names": [str(n) for n in getattr(names_from, "state_names", ())],
                        "input_names": [str(n) for n in getattr(names_from, "input_names", ())],
                        "n_parameters": int(getattr(model, "n_parameters", 0) or 0),
                        "backbone": backbone.to_dict() if isinstance(backbone, ExplicitModel) else None})


def _unpack(packed):
    if packed is None:
        return None
    kind, data = packed
    if kind == "explicit":
        return ExplicitModel.from_dict(data)
    backbone = ExplicitModel.from_dict(data["backbone"]) if data["backbone"] else None
    return ModelSummary(data["kind"], data["state_names"], data["input_names"], data["n_parameters"], backbone)


def _numbers(values: dict) -> dict:
    out = {}
    for key, value in values.items():
        try:
            out[str(key)] = float(value)
        except (TypeError, ValueError):
            pass
    return out


def _import_training(threads: int | None) -> None:
    """Import what the hybrid training needs (torch, torchdiffeq: ~1.4 s) and size torch's pool.

    Runs in a background thread of the child: a job that arrives meanwhile starts its backbone at
    once, and its training's own ``import torch`` waits for this one (Python's module locks). If
    this import fails, the training imports again and reports the error itself.
    """
    try:
        import torch
        import torch.func  # noqa: F401
        import torchdiffeq  # noqa: F401
    except Exception:  # noqa: BLE001 - the run's own import raises it where it can be reported
        return
    if threads:
        torch.set_num_threads(threads)


def _serve(conn, stop, threads: int | None) -> None:
    """Child process: import the engine, wait for one job, run it, report, exit."""
    # the parent decides when a run ends (Ctrl-C of a launch reaches the whole process group)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import pysindy  # noqa: F401  (the backbone's: ~1.1 s)

    from . import IdentConfig, IdentificationCancelled, make_estimator

    # a cold child (the node's first run) then takes its job without waiting for torch: measured
    # in the live benchmark, the first backbone came 4.3 s after the 12th trajectory when the
    # child imported everything first (0.5 s from a warm one)
    warming = threading.Thread(target=_import_training, args=(threads,), name="pisml-import", daemon=True)
    warming.start()
    conn.send(("ready", os.getpid()))
    try:
        job = conn.recv()
    except (EOFError, OSError):  # the parent went away or closed the worker unused
        return
    method, config, train, smallsignal = job

    def send(*message):
        conn.send(message)

    def callback(update: StageUpdate):
        send("update", update.stage, update.progress, update.epoch, _numbers(update.losses), _pack(update.model))

    try:
        try:
            estimator = make_estimator(method, IdentConfig.from_mapping(config))
            with blas_threads(threads):  # the BLAS pools' share (torch's is set in _import_training)
                estimator.fit(train, smallsignal, callback=callback, should_stop=stop.is_set)
            final = estimator.explicit_model_ if estimator.explicit_model_ is not None else estimator.model_
            send("done", _pack(final), _numbers(estimator.metrics_), getattr(estimator, "history_", {}), "")
        except IdentificationCancelled as err:
            send("cancelled", None, {}, {}, str(err))
        except (BrokenPipeError, EOFError, ConnectionError):
            raise
        except Exception as err:  # reported to the parent, which decides what to do
            send("failed", None, {}, {}, f"{type(err).__name__}: {err}")
    except (BrokenPipeError, EOFError, ConnectionError):
        pass  # the parent closed the worker: nobody to report to
    finally:
        conn.close()


class IdentificationWorker:
    """One identification run in a child process (started now, warm by the time it is used).

    Parameters
    ----------
    threads : int, optional
        Threads for torch and BLAS in the child (default: their own defaults).

    Examples
    --------
    >>> worker = IdentificationWorker(threads=1)
    >>> worker.submit("pisml", IdentConfig(), train)             # doctest: +SKIP
    >>> for item in worker.results():                            # doctest: +SKIP
    ...     print(item)   # StageUpdate ..., then a RunResult
    """

    def __init__(self, threads: int | None = None):
        context = multiprocessing.get_context("spawn")  # no fork of a multithreaded (ROS) parent
        self._stop = context.Event()
        self._conn, child = context.Pipe()
        self._process = context.Process(target=_serve, args=(child, self._stop, threads),
                                         name="pisml-identification", daemon=True)
        self._process.start()
        child.close()
        self.pid = self._process.pid
        self.submitted = False

    def submit(self, method: str, config, train, smallsignal=None) -> None:
        """Hand the child its one job (``config``: an IdentConfig or its dict)."""
        if self.submitted:
            raise RuntimeError("an IdentificationWorker runs one job; start a new one")
        config = config.to_dict() if hasattr(config, "to_dict") else dict(config)
        self._conn.send((method, config, train, smallsignal))
        self.submitted = True

    def cancel(self) -> None:
        """Ask the run to stop at its next progress check (the fit raises IdentificationCancelled)."""
        self._stop.set()

    def results(self, poll: float = 0.1, should_stop=None) -> Iterator[StageUpdate | RunResult]:
        """Stage updates as they come, then one :class:`RunResult` (also if the child dies).

        ``should_stop()``, checked every ``poll`` seconds, cancels the run when it turns true.
        """
        while True:
            if should_stop is not None and should_stop():
                self.cancel()
            try:
                if not self._conn.poll(poll):
                    if not self._process.is_alive() and not self._conn.poll(0):
                        yield RunResult("failed", error=f"identification process exited with code "
                                                        f"{self._process.exitcode}")
                        return
                    continue
                item = self._conn.recv()
            except (EOFError, OSError):
                self._process.join(1.0)
                yield RunResult("failed", error=f"identification process ended unexpectedly "
                                                f"(exit code {self._process.exitcode})")
                return
            kind = item[0]
            if kind == "ready":
                continue
            if kind == "update":
                _, stage, progress, epoch, losses, packed = item
                yield StageUpdate(stage, progress, epoch, losses, _unpack(packed))
                continue
            _, packed, metrics, history, error = item
            yield RunResult(kind, _unpack(packed), metrics, history, error)
            return

    def close(self, timeout: float = 10.0) -> None:
        """End the child: cancel a run, wait ``timeout`` s, then terminate it."""
        self._stop.set()
        with contextlib.suppress(OSError):
            self._conn.close()
        self._process.join(timeout)
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(2.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(1.0)
