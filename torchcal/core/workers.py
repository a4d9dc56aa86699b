"""Independent pieces of a fit side by side, on the cores a single fit leaves idle.

A fit runs on one intra-op thread (:mod:`torchcal.core.threads`: its operations are too small to
split), so on a machine with more cores the others sit idle while, for example, the heads'
cross-validation trains an MLP after an MMA-ELM on the same fold although neither needs the
other. :func:`side_by_side` runs such pieces at once: the first in this process, the others in
worker processes of loky's reusable executor (the process pool of joblib and scikit-learn, started
by fork + exec, so no OpenMP state is inherited). Each piece computes exactly what it would compute
here, on one thread, from the same inputs and seeds: the results are the same to the bit.

How many processes (``jobs``): the ``jobs`` option of a command, else the ``TORCHCAL_JOBS``
environment variable, else the cores this process may run on (:func:`resolve_jobs`). ``1`` runs
everything in this process. A study's workers fit with ``jobs=1``: they are the parallelism there.

Workers start in the background (:func:`warm_up`) while this process does the serial part of a
fit, so their imports (torch, about 2 s) do not delay the pieces. They ignore Ctrl-C: the main
process handles it and stops them (:func:`stop_workers`). Idle workers exit after
:data:`IDLE_TIMEOUT_S`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

#: Environment variable that sets the default number of processes of a fit.
JOBS_ENV = "TORCHCAL_JOBS"
#: Seconds an idle worker waits for the next piece before it exits.
IDLE_TIMEOUT_S = 120


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity where the platform tells it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not every platform has an affinity mask
        return max(1, os.cpu_count() or 1)


def resolve_jobs(requested: int | None) -> int:
    """Processes a fit may use: ``requested``, else ``$TORCHCAL_JOBS``, else :func:`usable_cores`."""
    if requested is not None:
        return max(1, int(requested))
    env = os.environ.get(JOBS_ENV, "").strip()
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            from torchcal.core.errors import TorchcalError

            raise TorchcalError(f"{JOBS_ENV} must be a whole number of processes, got {env!r}") from None
    return usable_cores()


def _ignore_interrupt() -> None:
    """Worker start-up: Ctrl-C is the main process's to handle (it stops the workers)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


_current: list[Any] = []  # the executor last handed out, for stop_workers


def _executor(workers: int):
    from joblib.externals.loky import get_reusable_executor

    # one intra-op thread per worker, like the fit in the main process (core.threads); set before any import
    threads = dict.fromkeys(("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"), "1")
    executor = get_reusable_executor(max_workers=workers, timeout=IDLE_TIMEOUT_S, initializer=_ignore_interrupt,
                                     env=threads)
    _current[:] = [executor]
    return executor


def _import(modules: Sequence[str]) -> None:
    import importlib

    for name in modules:
        importlib.import_module(name)


def warm_up(jobs: int, modules: Sequence[str]) -> None:
    """Start ``jobs - 1`` workers now and import ``modules`` in them, without waiting for either."""
    if jobs > 1:
        executor = _executor(jobs - 1)
        for _ in range(jobs - 1):
            executor.submit(_import, tuple(modules))


def stop_workers() -> None:
    """Stop the workers at once, pieces under way included (after an error or an interrupt here)."""
    while _current:
        _current.pop().shutdown(wait=False, kill_workers=True)


def side_by_side(fn: Callable[..., Any], tasks: Sequence[tuple], jobs: int) -> list[Any]:
    """``[fn(*task) for task in tasks]``, the first task here and the others in up to ``jobs - 1`` workers.

    ``fn`` and the tasks' arguments travel by pickle: give module-level functions and numpy arrays
    (not torch tensors, whose pickling may go through shared memory). With ``jobs == 1`` or one task,
    everything runs here, in order. An error in any task is raised here, as it was raised there.
    """
    if jobs <= 1 or len(tasks) <= 1:
        return [fn(*task) for task in tasks]
    executor = _executor(min(jobs - 1, len(tasks) - 1))
    try:
        futures = [executor.submit(fn, *task) for task in tasks[1:]]
        first = fn(*tasks[0])
        return [first] + [future.result() for future in futures]
    except BaseException:
        stop_workers()
        raise


class Pending:
    """A piece started by :func:`in_background`; :meth:`result` waits for it and returns (or raises) what it did."""

    def __init__(self, future: Any = None, value: Any = None) -> None:
        self._future, self._value = future, value

    def result(self) -> Any:
        if self._future is not None:
            self._value, self._future = self._future.result(), None
        return self._value


@contextmanager
def in_background(fn: Callable[..., Any], *args: Any, jobs: int) -> Iterator[Pending]:
    """``fn(*args)`` in a worker while the body runs here; with ``jobs == 1``, here and first.

    Leaving the body by an error or an interrupt stops the worker, the piece under way included.
    """
    pending = Pending(value=fn(*args)) if jobs <= 1 else Pending(future=_executor(1).submit(fn, *args))
    try:
        yield pending
        pending.result()
    except BaseException:
        if jobs > 1:
            stop_workers()
        raise
