"""The gap workflow's lockstep: searches run side by side, their calls answered in shared batches."""
import threading

import pytest

from pisml_ros.gap.lockstep import Lockstep


def _run(lockstep, tasks, timeout=20.0):
    # a lost wake-up would hang the tasks: fail instead
    out = {}

    def target():
        try:
            out["results"] = lockstep.run(tasks)
        except BaseException as err:
            out["error"] = err

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(timeout)
    assert not thread.is_alive(), "the lockstep hung"
    if "error" in out:
        raise out["error"]
    return out["results"]


def _search(start, calls):
    # a stand-in for least_squares: each call depends on the previous answer
    def task(call):
        value = start
        for _ in range(calls):
            value = call(value)
        return value
    return task


def test_calls_are_batched_while_every_task_runs_and_answers_are_each_callers_own():
    sizes = []

    def batch(items):
        sizes.append(len(items))
        return [2 * item + 1 for item in items]

    results = _run(Lockstep(batch), [_search(1, 3), _search(10, 5), _search(100, 1), _search(7, 0)])
    assert results == [15, 351, 201, 7]  # as each search alone
    # three calls together while all three run, then two, then one
    assert sizes == [3, 2, 2, 1, 1]


def test_a_failing_item_fails_only_its_caller_and_a_failing_task_is_raised_after_all_end():
    def batch(items):
        if 0 in items:
            raise ValueError("cannot simulate 0")
        return items

    finished = []

    def tolerant(call):
        try:
            call(0)
        except ValueError:
            finished.append("tolerant")
        return "done"

    def failing(call):
        call(0)

    def slow(call):
        for _ in range(4):
            call(1)
        finished.append("slow")

    def raises_at_once(call):
        raise KeyError("before any call")

    with pytest.raises(ValueError, match="cannot simulate 0"):  # the first failing task's error
        _run(Lockstep(batch), [tolerant, failing, raises_at_once, slow])
    assert sorted(finished) == ["slow", "tolerant"]


def test_a_batch_that_answers_too_few_items_fails_those_calls_instead_of_hanging_them():
    def short(items):
        return items[:1] if len(items) > 1 else items

    assert _run(Lockstep(short), [_search(1, 2), _search(2, 2)]) == [1, 2]  # answered one by one instead


def test_a_lockstep_map_batches_the_columns_of_scipys_jacobian_and_changes_no_number():
    import numpy as np
    import scipy.optimize

    from pisml_ros.gap.lockstep import LockstepMap, current_call

    sizes = []

    def batch(items):
        sizes.append(len(items))
        return [np.array([x[0] - 1.0, x[1] ** 2 - 4.0, x[0] * x[2] - 3.0]) for x in items]

    def residuals(x):
        call = current_call()  # inside the map's tasks: joined with the other columns
        return call(x) if call is not None else batch([x])[0]

    alone = scipy.optimize.least_squares(residuals, [0.5, 1.0, 1.0], method="trf", diff_step=1e-3)
    sizes.clear()
    mapped = scipy.optimize.least_squares(residuals, [0.5, 1.0, 1.0], method="trf", diff_step=1e-3,
                                          workers=LockstepMap(batch))
    assert np.array_equal(alone.x, mapped.x) and alone.nfev == mapped.nfev
    assert 3 in sizes  # the three columns of a Jacobian in one batch
    np.testing.assert_allclose(mapped.x, [1.0, 2.0, 3.0], atol=1e-6)
