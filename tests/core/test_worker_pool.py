"""Pieces side by side in worker processes: the same results as one after the other, errors raised
here, workers stopped after an error, and the number of processes from option, environment or cores."""

from __future__ import annotations

import os
import signal
import sys
import time

import numpy as np
import pytest
from cloudpickle import register_pickle_by_value

from torchcal.core.errors import DataError, TorchcalError
from torchcal.core.workers import (
    JOBS_ENV,
    import_while_waiting,
    in_background,
    in_worker,
    ready_workers,
    resolve_jobs,
    side_by_side,
    stop_workers,
    usable_cores,
    warm_up,
)

# the workers cannot import this test module by name (pytest puts its folder on the path here only):
# its functions travel by value
register_pickle_by_value(sys.modules[__name__])


def _square_with_pid(x: np.ndarray) -> tuple[np.ndarray, int]:
    return x * x, os.getpid()


def _sleep_then_square(x: np.ndarray, seconds: float) -> tuple[np.ndarray, int]:
    time.sleep(seconds)
    return x * x, os.getpid()


def _fail(message: str) -> None:
    if message:
        raise DataError(message)


def test_jobs_from_option_then_environment_then_cores(monkeypatch):
    monkeypatch.setenv(JOBS_ENV, "3")
    assert resolve_jobs(2) == 2 and resolve_jobs(None) == 3
    monkeypatch.delenv(JOBS_ENV)
    assert resolve_jobs(None) == usable_cores() >= 1
    monkeypatch.setenv(JOBS_ENV, "two")
    with pytest.raises(TorchcalError, match="TORCHCAL_JOBS must be a whole number"):
        resolve_jobs(None)


@pytest.fixture
def one_worker():
    warm_up(2, ["numpy"], wait=True)
    yield
    stop_workers()


@pytest.mark.parametrize("jobs", [1, 2])
def test_side_by_side_gives_the_serial_results_in_order(one_worker, jobs):
    tasks = [(np.arange(k, k + 4, dtype=np.float64), 0.2) for k in range(6)]
    results = side_by_side(_sleep_then_square, tasks, jobs)
    for (x, _), (squared, _pid) in zip(tasks, results):
        np.testing.assert_array_equal(squared, x * x)
    here = [pid == os.getpid() for _squared, pid in results]
    if jobs == 1:
        assert all(here)
    else:  # this process from the first task on, the worker from the last back, each about half
        assert here[:2] == [True, True] and here[-2:] == [False, False]
        assert here == sorted(here, reverse=True)


def test_side_by_side_does_not_wait_for_a_busy_worker(one_worker):
    """A worker busy with a piece of in_background is sent a task only when it has finished it:
    this process does the tasks meanwhile, and the worker joins in for the rest."""
    with in_background(_sleep_then_square, np.ones(1), 0.6, jobs=2):
        results = side_by_side(_sleep_then_square, [(np.full(2, float(k)), 0.2) for k in range(12)], 2)
        here = [pid == os.getpid() for _squared, pid in results]
        assert here[:4] == [True] * 4 and not here[-1] and here == sorted(here, reverse=True)
    with in_background(_sleep_then_square, np.ones(1), 3.0, jobs=2):
        started = time.perf_counter()
        results = side_by_side(_sleep_then_square, [(np.full(2, float(k)), 0.1) for k in range(6)], 2)
        assert {pid for _squared, pid in results} == {os.getpid()} and time.perf_counter() - started < 2.0
    np.testing.assert_array_equal([squared[0] for squared, _pid in results], np.arange(6.0) ** 2)


@pytest.fixture
def slow_starting_worker(tmp_path, monkeypatch):
    """``start(seconds)``: one worker whose warm-up import takes ``seconds`` (a module that sleeps;
    a worker gets this process's ``sys.path``)."""
    monkeypatch.syspath_prepend(str(tmp_path))

    def start(seconds: float) -> None:
        stop_workers()
        name = f"slow_start_{int(seconds * 1000)}"
        (tmp_path / f"{name}.py").write_text(f"import time\ntime.sleep({seconds})\n")
        warm_up(2, [name])

    yield start
    stop_workers()


def test_a_starting_worker_joins_in_once_ready(slow_starting_worker):
    slow_starting_worker(1.0)
    assert ready_workers() == 0
    results = side_by_side(_sleep_then_square, [(np.full(2, float(k)), 0.2) for k in range(15)], 2)
    here = [pid == os.getpid() for _squared, pid in results]
    assert here[:5] == [True] * 5 and not here[-1] and here == sorted(here, reverse=True)


def test_pieces_wait_for_no_worker_that_is_starting(slow_starting_worker):
    slow_starting_worker(4.0)
    started = time.perf_counter()
    results = side_by_side(_sleep_then_square, [(np.full(2, float(k)), 0.1) for k in range(5)], 2)
    assert {pid for _squared, pid in results} == {os.getpid()} and time.perf_counter() - started < 3.0


def test_pieces_wait_for_no_worker_that_is_not_ready():
    stop_workers()
    assert ready_workers() == 0
    results = side_by_side(_square_with_pid, [(np.ones(2),), (np.ones(3),)], 2)
    assert {pid for _squared, pid in results} == {os.getpid()}


def test_an_error_in_a_worker_is_raised_here_and_stops_the_workers(one_worker):
    with pytest.raises(DataError, match="row 7"):
        side_by_side(_fail, [("",), ("row 7 of the worker's file",)], 2)  # the first, here, succeeds
    assert ready_workers() == 0
    warm_up(2, ["numpy"], wait=True)  # the next fit starts them again
    squared, pid = side_by_side(_square_with_pid, [(np.ones(2),), (np.full(2, 3.0),)], 2)[1]
    np.testing.assert_array_equal(squared, [9.0, 9.0])
    assert pid != os.getpid()


def test_in_background_runs_beside_the_body_or_first(one_worker):
    with in_background(_square_with_pid, np.full(3, 2.0), jobs=2) as pending:
        here = os.getpid()
    squared, pid = pending.result()
    np.testing.assert_array_equal(squared, [4.0, 4.0, 4.0])
    assert pid != here
    with in_background(_square_with_pid, np.full(2, 5.0), jobs=1) as pending:
        assert pending.result()[1] == os.getpid()  # already computed when the body starts


def test_in_background_raises_the_pieces_error_when_the_body_ends(one_worker):
    with pytest.raises(DataError, match="bad column q3"), in_background(_fail, "bad column q3", jobs=2):
        pass


def test_a_piece_whose_worker_is_killed_is_done_here(one_worker):
    worker = side_by_side(_square_with_pid, [(np.ones(1),), (np.ones(1),)], 2)[1][1]
    with in_background(_sleep_then_square, np.full(2, 3.0), 2.0, jobs=2) as pending:
        time.sleep(0.3)
        os.kill(worker, signal.SIGKILL)  # the OOM killer, or a user
    squared, pid = pending.result()
    np.testing.assert_array_equal(squared, [9.0, 9.0])
    assert pid == os.getpid() and ready_workers() == 0


def _where(_: int) -> bool:
    return in_worker()


def test_a_worker_knows_it_is_one(one_worker):
    assert side_by_side(_where, [(0,), (1,)], 2) == [False, True]


def test_modules_named_for_later_are_imported_while_this_process_waits(one_worker, tmp_path, monkeypatch):
    (tmp_path / "needed_later_module.py").write_text("import time\nIMPORTED_AT = time.perf_counter()\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import_while_waiting("needed_later_module")
    assert "needed_later_module" not in sys.modules
    with in_background(_sleep_then_square, np.ones(1), 1.0, jobs=2) as pending:
        pass
    finished = time.perf_counter()
    assert pending.result()[1] != os.getpid()
    imported_at = sys.modules["needed_later_module"].IMPORTED_AT  # here, while the piece (1 s) ran there
    assert imported_at < finished - 0.5
    monkeypatch.delitem(sys.modules, "needed_later_module")
