"""Several blocking searches whose expensive calls are gathered into batches.

scipy's ``least_squares`` asks for one residual at a time, and the gap workflow
fits several candidates, each with its own ``least_squares``. The simulation
behind a residual costs about the same for one plant as for a stack of them
(:class:`~pisml_ros.plant.stack.PlantStack`), so the candidates' searches run in
threads, and each call they make waits until every search still running has
made one: then all of them are simulated in one pass. Each search sees the same
numbers as it would alone (a stack gives each row its own plant's bits; Padé-2 delays
aside, whose stacked rows round apart by ~1e-14); only the wall time changes. :class:`LockstepMap` does
the same for the columns of a finite-difference Jacobian (scipy's ``workers``).
"""
from __future__ import annotations

import threading
from typing import Any, Callable, Iterable, Sequence

_current = threading.local()


def current_call():
    """The :meth:`Lockstep.call` of the task running in this thread, or None outside a lockstep."""
    return getattr(_current, "call", None)


class Lockstep:
    """Run tasks side by side, their calls to :meth:`call` answered in batches.

    Parameters
    ----------
    batch : callable
        ``batch(items) -> results``, one result per item, in order.
    """

    def __init__(self, batch: Callable[[list], Sequence]):
        self._batch = batch
        self._lock = threading.Condition()
        self._pending: list = []
        self._active = 0

    def run(self, tasks: Sequence[Callable[[Callable[[Any], Any]], Any]]) -> list:
        """Run ``task(call)`` for each task, each in its own thread; their return values, in order.

        A task's exception is raised here once every task has ended (the first task's, where
        several fail).
        """
        results: list = [None] * len(tasks)
        errors: dict = {}
        self._active = len(tasks)

        def work(index, task):
            _current.call = self.call
            try:
                results[index] = task(self.call)
            except BaseException as err:  # re-raised in the caller's thread
                errors[index] = err
            finally:
                with self._lock:
                    self._active -= 1
                    self._answer_if_all_waiting()

        threads = [threading.Thread(target=work, args=(k, task), daemon=True) for k, task in enumerate(tasks)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        if errors:
            raise errors[min(errors)]
        return results

    def call(self, item):
        """Submit one item; returns its result once the batch it joined has run."""
        slot: dict = {}
        with self._lock:
            self._pending.append((item, slot))
            self._answer_if_all_waiting()
            while not slot:
                self._lock.wait()
        if "error" in slot:
            raise slot["error"]
        return slot["result"]

    def _answer_if_all_waiting(self):
        # called with the lock held: every running task is waiting for an answer, so none can add one
        if not self._pending or len(self._pending) < self._active:
            return
        batch, self._pending = self._pending, []
        try:
            try:
                answers = [{"result": answer} for answer in self._batch([item for item, _ in batch])]
                if len(answers) != len(batch):
                    raise RuntimeError(f"a batch of {len(batch)} items gave {len(answers)} answers")
            except Exception:  # one item's failure must not fail the others: answer each alone
                answers = [self._alone(item) for item, _ in batch]
            for (_, slot), answer in zip(batch, answers):
                slot.update(answer)
        except BaseException as err:  # whatever happens here, no caller may wait forever
            for _, slot in batch:
                if not slot:
                    slot["error"] = err
            raise
        finally:
            self._lock.notify_all()

    def _alone(self, item) -> dict:
        try:
            return {"result": self._batch([item])[0]}
        except Exception as err:
            return {"error": err}


class LockstepMap:
    """A map-like callable (scipy's ``workers``): ``f`` over the items side by side, each in a
    :class:`Lockstep` task, so that the calls ``f`` makes through :func:`current_call` share batches.

    Parameters
    ----------
    batch : callable
        As for :class:`Lockstep`.
    """

    def __init__(self, batch: Callable[[list], Sequence]):
        self._batch = batch

    def __call__(self, f: Callable, items: Iterable) -> list:
        return Lockstep(self._batch).run([lambda call, item=item: f(item) for item in items])
