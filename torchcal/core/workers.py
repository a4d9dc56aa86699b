"""Independent pieces of a fit side by side, on the cores a single fit leaves idle.

A fit runs on one intra-op thread (:mod:`torchcal.core.threads`: its operations are too small to
split), so on a machine with more cores the others sit idle while, for example, the heads'
cross-validation trains an MLP after an MMA-ELM on the same fold although neither needs the
other. :func:`side_by_side` shares such pieces between this process and worker processes of
loky's reusable executor (the process pool of joblib and scikit-learn, started by fork + exec, so
no OpenMP state is inherited); :func:`in_background` runs one piece there while this process goes on. Each piece computes exactly what it would compute
here, on one thread, from the same inputs and seeds: the results are the same to the bit.

How many processes (``jobs``): the ``jobs`` option of a command, else the ``TORCHCAL_JOBS``
environment variable, else the cores this process may run on (:func:`resolve_jobs`). ``1`` runs
everything in this process. A study's workers fit with ``jobs=1``: they are the parallelism there.

Workers start in the background (:func:`warm_up`) while this process does the serial part of a
fit; their imports (torch, about 2 s) delay nothing, since pieces go to a worker only once it is
ready (until then this process does them all). They ignore Ctrl-C: the main process handles it
and stops them (:func:`stop_workers`). Idle workers exit after :data:`IDLE_TIMEOUT_S`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

#: Environment variable that sets the default number of processes of a fit.
JOBS_ENV = "TORCHCAL_JOBS"
#: Seconds an idle worker waits for the next piece before it exits.
IDLE_TIMEOUT_S = 60


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


_in_worker = [False]  # set in a worker process when it starts


def in_worker() -> bool:
    """Whether this process is one of the workers (its pieces run beside the main process's work)."""
    return _in_worker[0]


def _worker_start() -> None:
    """Worker start-up: Ctrl-C is the main process's to handle (it stops the workers)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _in_worker[0] = True


@contextmanager
def _interrupts_ignored_by_new_workers() -> Iterator[None]:
    """Workers started in the body inherit an ignored SIGINT, so that a Ctrl-C of the terminal (sent
    to the whole process group) reaches them not even while they import, before their initializer.
    Only the main thread may set a handler; elsewhere the initializer alone does it."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


#: The pool of this process: its executor, its number of workers and the futures of its warm-up tasks.
_pool: dict[str, Any] = {}


#: Modules this process will need later, imported the next time it waits for a worker (:func:`import_while_waiting`).
_later: list[str] = []


def import_while_waiting(*modules: str) -> None:
    """Name modules this process will import later (a report's plotting, say): it imports them the
    next time it waits for a worker (for the last tasks of :func:`side_by_side`, the piece of
    :func:`in_background`), time it would otherwise spend idle. Each is imported once, in order."""
    _later.extend(m for m in modules if m not in _later)


def _use_the_wait(futures: Sequence[Any]) -> None:
    """Import what :func:`import_while_waiting` named, if this process is about to wait for ``futures``."""
    if not _later or all(f.done() for f in futures):
        return
    import importlib

    while _later:
        importlib.import_module(_later.pop(0))


def _import(modules: Sequence[str]) -> None:
    import importlib

    for name in modules:
        importlib.import_module(name)


def warm_up(jobs: int, *module_groups: Sequence[str], wait: bool = False) -> None:
    """Start ``jobs - 1`` workers now and import each group of modules in them (a group after
    another, in order), without waiting for either unless ``wait``.

    Pieces go to workers only once one has finished a warm-up group (:func:`ready_workers`): until
    then this process does them, so a fit never waits for a worker to start.
    """
    if jobs <= 1:
        return
    from joblib.externals.loky import get_reusable_executor

    # one intra-op thread per worker, like the fit in the main process (core.threads); set before any import
    threads = dict.fromkeys(("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"), "1")
    groups = [tuple(group) for group in module_groups or [()]]
    with _interrupts_ignored_by_new_workers():
        executor = get_reusable_executor(max_workers=jobs - 1, timeout=IDLE_TIMEOUT_S, initializer=_worker_start,
                                         env=threads)
        same = _pool.get("executor") is executor
        # a group this pool has imported or queued already is not queued again (a command and its fit
        # both start the workers): fewer pending items, fewer for an interrupt's shutdown to race with
        queued: dict[tuple, Any] = _pool.get("queued", {}) if same else {}
        futures = [queued.setdefault(group, executor.submit(_import, group)) for group in groups if group not in queued]
    earlier = _pool.get("ready", []) if same else []
    _pool.update(executor=executor, workers=jobs - 1, ready=earlier + futures, queued=queued)
    if wait:
        for group in groups:
            queued[group].result()


def import_in_workers(*module_groups: Sequence[str]) -> None:
    """Queue the import of each group of modules in the workers already started (nothing without them)."""
    executor = _pool.get("executor")
    if executor is not None:
        _pool["ready"] += [executor.submit(_import, tuple(group)) for group in module_groups]


def ready_workers() -> int:
    """Workers of this process's pool that have started and imported a warm-up group (0: none yet)."""
    futures = _pool.get("ready", [])
    started = any(f.done() and not f.cancelled() and f.exception() is None for f in futures)
    return int(_pool["workers"]) if started else 0


def workers_for(jobs: int) -> int:
    """Workers that may take pieces now with ``jobs`` processes: ready ones (:func:`ready_workers`), at most ``jobs - 1``."""
    return max(0, min(jobs - 1, ready_workers()))


def started_workers(jobs: int) -> int:
    """Workers of this process's pool, ready or still starting, at most ``jobs - 1`` (0: none, or the
    start of every one failed)."""
    futures = _pool.get("ready", [])
    failed = bool(futures) and all(f.done() and (f.cancelled() or f.exception() is not None) for f in futures)
    return 0 if failed or "executor" not in _pool else max(0, min(jobs - 1, int(_pool["workers"])))


def stop_workers() -> None:
    """Stop the workers at once, pieces under way included: after an error or an interrupt here, and
    when a command ends (one that ends by ``os._exit`` would otherwise leave them waiting for work)."""
    executor = _pool.pop("executor", None)
    _pool.clear()
    if executor is not None:
        executor.shutdown(wait=True, kill_workers=True)


def _busy_pieces() -> list[Any]:
    """Pieces of :func:`in_background` that a worker has not finished yet."""
    busy = [f for f in _pool.get("busy", []) if not f.done()]
    if "busy" in _pool:
        _pool["busy"] = busy
    return busy


def side_by_side(fn: Callable[..., Any], tasks: Sequence[tuple], jobs: int) -> list[Any]:
    """``[fn(*task) for task in tasks]``, shared between this process and up to ``jobs - 1`` workers.

    This process takes the tasks from the first on, the workers from the last back, one at a time
    each (a worker is sent its next task when it has finished one), until they meet: neither side
    waits while tasks are left, whatever the tasks cost. A worker still starting, or busy with a
    piece of :func:`in_background`, is sent its first task once it is free (until then this
    process goes on alone). Each task is done once, from the
    same inputs, so the results do not depend on where it ran. ``fn`` and the tasks' arguments
    travel by pickle (cloudpickle: functions, arrays, tensors, fits). With ``jobs == 1``, one task
    or no worker started (:func:`started_workers`), everything runs here, in order. An error in any
    task is raised here, as it was raised there; a task whose worker was lost is done here.
    """
    workers = min(started_workers(jobs), len(tasks) - 1)
    if workers < 1:
        return [fn(*task) for task in tasks]
    share = _Share(fn, tasks, workers)
    try:
        results = {}
        while (i := share.claim_first()) is not None:
            results[i] = fn(*tasks[i])
        sent = share.sent()
        _use_the_wait(list(sent.values()))
        for i, future in sent.items():
            results[i] = _result_or_here(future, fn, tasks[i])
        return [results[i] for i in range(len(tasks))]
    except BaseException:
        share.stop()
        stop_workers()
        raise


class _Share:
    """The tasks of one :func:`side_by_side`: this process claims them from the front, a thread here
    sends them to the workers from the back, each worker's next when its last is done (a task sent
    is out of reach: loky's queue cannot take back what a worker has been given)."""

    def __init__(self, fn: Callable[..., Any], tasks: Sequence[tuple], workers: int) -> None:
        import threading

        self._fn, self._tasks = fn, tasks
        self._lock = threading.Lock()
        self._front, self._back = 0, len(tasks)  # next task here; one past the next task for a worker
        self._futures: dict[int, Any] = {}
        self._stopped = False
        busy = _busy_pieces()
        first: list[Any] = []
        if ready_workers():  # else the thread below sends them once a worker is ready
            with _interrupts_ignored_by_new_workers():  # a worker that timed out idle is started again here
                first = [f for f in (self._send() for _ in range(workers - len(busy))) if f is not None]
        self._sender = threading.Thread(target=self._send_as_workers_finish, args=(first, workers, busy),
                                        name="torchcal-side-by-side", daemon=True)
        self._sender.start()

    def claim_first(self) -> int | None:
        with self._lock:
            if self._front >= self._back:
                return None
            self._front += 1
            return self._front - 1

    def _send(self) -> Any:
        with self._lock:
            if self._stopped or self._back <= self._front:
                return None
            self._back -= 1
            i = self._back
            future = _pool["executor"].submit(self._fn, *self._tasks[i])
            self._futures[i] = future
            return future

    def _send_as_workers_finish(self, sent: list[Any], workers: int, busy: list[Any]) -> None:
        """Send a task to every worker that has finished its start, a task, or a piece of
        :func:`in_background` (``busy``), until none is left to send."""
        from concurrent.futures import FIRST_COMPLETED, wait

        if not ready_workers():  # still starting: the first tasks go once one is ready
            wait(_pool.get("ready", []), return_when=FIRST_COMPLETED)
            if not ready_workers():
                return  # their start failed: this process does every task
        free = workers - len(sent) - len(busy)
        watched = sent + busy
        while True:
            for _ in range(max(free, 0)):
                try:
                    future = self._send()
                except (RuntimeError, KeyError):  # the pool was shut down (an error or Ctrl-C here)
                    return
                if future is None:
                    return  # nothing left to send: this process has claimed the rest
                watched.append(future)
            if not watched:
                return
            done, pending = wait(watched, return_when=FIRST_COMPLETED)
            watched = list(pending)
            ours = set(self.sent().values())
            if any(f in ours and (f.cancelled() or f.exception() is not None) for f in done):
                return  # the error is raised here when its result is asked for; nothing more is sent
            free = len(done)

    def sent(self) -> dict[int, Any]:
        """The tasks sent to workers, once no more can be (this process has claimed the rest): the
        sending thread may still wait for a worker to start, with nothing left to send."""
        with self._lock:
            return dict(self._futures)

    def stop(self) -> None:
        with self._lock:
            self._stopped = True


def _result_or_here(future: Any, fn: Callable[..., Any], args: tuple) -> Any:
    """The piece's result from its worker; if the worker was lost (killed, out of memory) or could not
    take the piece, the workers are stopped and the piece is done here."""
    from concurrent.futures import BrokenExecutor

    try:
        return future.result()
    except BrokenExecutor:
        stop_workers()
        return fn(*args)


class Pending:
    """A piece started by :func:`in_background`; :meth:`result` waits for it and returns (or raises) what it did."""

    def __init__(self, fn: Callable[..., Any], args: tuple, future: Any = None) -> None:
        self._fn, self._args, self._future = fn, args, future
        self._value = fn(*args) if future is None else None

    def result(self) -> Any:
        if self._future is not None:
            _use_the_wait([self._future])
            self._value, self._future = _result_or_here(self._future, self._fn, self._args), None
        return self._value


@contextmanager
def in_background(fn: Callable[..., Any], *args: Any, jobs: int) -> Iterator[Pending]:
    """``fn(*args)`` in a ready worker while the body runs here; with ``jobs == 1`` or no ready worker,
    here and first.

    Leaving the body by an error or an interrupt stops the worker, the piece under way included.
    """
    there = workers_for(jobs) > 0
    if there:
        with _interrupts_ignored_by_new_workers():
            future = _pool["executor"].submit(fn, *args)
        _pool.setdefault("busy", []).append(future)  # side_by_side sends nothing to its worker meanwhile
        pending = Pending(fn, args, future)
    else:
        pending = Pending(fn, args)
    try:
        yield pending
        pending.result()
    except BaseException:
        if there:
            stop_workers()
        raise
