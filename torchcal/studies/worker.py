"""One study worker: take trials until the database holds the budget of finished trials.

Every worker, local or on another machine, runs the same loop. Under the study lock
(:mod:`torchcal.studies.lock`) it fails trials whose heartbeat went stale (Optuna queues each again
as WAITING, with its parameters), counts the trials as the database has them and decides:

* ``stop`` when ``n_trials`` trials are finished (complete or pruned);
* ``wait`` when the finished and running trials fill the budget: a running trial either finishes
  or, if its worker died, goes stale and is queued again, and then this worker runs it;
* ``run`` otherwise: Optuna takes a queued trial first (a retry, the default configuration) and
  only then samples a new one. The lock is handed back as soon as the trial is taken.

A queued retry therefore counts as a slot still to fill, and is run by whichever worker reaches it
first: one that kept running or one started again. A new trial taken after the lock was lost (a
server restart ends the lock's session) is failed before it draws its parameters: another worker may
have read the same counts and drawn the same configuration. A database server that goes away is retried for
``reconnect_s``; past that the worker stops with a one-line message and the study resumes when the
command is run again.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

from torchcal.core.errors import TorchcalError
from torchcal.studies.lock import StudyLock
from torchcal.studies.objective import StudyObjective
from torchcal.studies.spec import StudyConfig
from torchcal.studies.storage import make_sampler, open_study, shown_url, storage_url

MAX_CONSECUTIVE_FAILURES = 3


class LockLostError(TorchcalError):
    """The study lock was lost (its database session ended) between reading the counts and taking a trial."""


def counts(study) -> dict[str, int]:
    """Trials per state (``COMPLETE``, ``PRUNED``, ``FAIL``, ``RUNNING``, ``WAITING``) in the database."""
    from optuna.trial import TrialState

    out = {state.name: 0 for state in TrialState}
    for trial in study.get_trials(deepcopy=False):
        out[trial.state.name] += 1
    return out


def finished(c: dict[str, int]) -> int:
    """Trials that count toward the budget: complete or pruned."""
    return c["COMPLETE"] + c["PRUNED"]


def next_step(c: dict[str, int], n_trials: int) -> str:
    """``stop``, ``wait`` or ``run`` for counts ``c`` (see the module docstring)."""
    if finished(c) >= n_trials:
        return "stop"
    if finished(c) + c["RUNNING"] >= n_trials:
        return "wait"
    return "run"


def _database_errors() -> tuple[type[BaseException], ...]:
    from optuna.exceptions import StorageInternalError
    from sqlalchemy.exc import SQLAlchemyError

    return (SQLAlchemyError, StorageInternalError)


def _database_cause(exc: BaseException) -> BaseException | None:
    """The database error behind ``exc``, if any (Optuna may raise another error while handling one)."""
    errors = _database_errors()
    seen = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, errors):
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


def _taken_over(exc: BaseException) -> bool:
    """Whether ``exc`` is Optuna refusing to record a trial another worker failed (its heartbeat went stale).

    Optuna raises ``UpdateFinishedTrialError`` when the objective writes to such a trial; recording
    its outcome, ``ValueError("Cannot tell a FAIL trial.")`` when the objective raised and
    ``AssertionError("Should not reach.")`` when it returned a value. ``Worker.run`` also checks
    that the trial is failed in the database before it goes on.
    """
    from optuna.exceptions import UpdateFinishedTrialError

    return (isinstance(exc, UpdateFinishedTrialError)
            or (isinstance(exc, ValueError) and str(exc).startswith("Cannot tell a "))
            or (isinstance(exc, AssertionError) and str(exc) == "Should not reach."))


def _first_line(exc: BaseException) -> str:
    cause = exc.__cause__ or exc
    text = str(cause).strip().splitlines()
    return text[0] if text else type(cause).__name__


def _quiet_heartbeat_errors() -> None:
    """A heartbeat thread that loses the database prints one line, not a traceback."""
    errors = _database_errors()
    previous = threading.excepthook

    def hook(args) -> None:
        if isinstance(args.exc_value, errors):
            print(f"study: a trial's heartbeat could not reach the database ({_first_line(args.exc_value)})",
                  file=sys.stderr)
            return
        previous(args)

    threading.excepthook = hook


class _OneLine(logging.Filter):
    """Optuna logs a failed trial with its traceback; the message already names the error."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.exc_info, record.exc_text = None, None
        return True


def _one_line_trial_failures() -> None:
    logger = logging.getLogger("optuna")
    if not any(isinstance(f, _OneLine) for f in logger.filters):
        logger.addFilter(_OneLine())
    for handler in logger.handlers:
        if not any(isinstance(f, _OneLine) for f in handler.filters):
            handler.addFilter(_OneLine())


class Worker:
    """The loop of one worker process over the shared study (see the module docstring)."""

    def __init__(self, base, config: StudyConfig, study_dir: Path) -> None:
        self.config, self.study_dir = config, Path(study_dir)
        self.url = storage_url(config, self.study_dir)
        self.study = open_study(config, self.study_dir)
        self.lock = StudyLock(self.url, config.name, self.study_dir)
        self.objective = StudyObjective(base, config, self.study_dir, on_start=self._taken)
        self.current: int | None = None
        self.counted = 0  # trials in the database when this worker last decided to run one
        self.lock_lost = False

    def _taken(self, trial) -> None:
        self.current = trial.number
        held = self.lock.held()
        self.lock.release()
        # A queued trial was taken atomically by Optuna (its number is below the count). A new one's
        # sampler was seeded from counts another worker may have read too once the lock was gone.
        self.lock_lost = not held and trial.number >= self.counted
        if self.lock_lost:
            raise LockLostError(f"the study lock was lost (the database session ended) before trial {trial.number} "
                                "drew its parameters; it is given up and another trial is drawn")

    def _step(self) -> str:
        """Decide under the lock, and run one trial when there is one to run."""
        import optuna

        self.lock.acquire()
        try:
            optuna.storages.fail_stale_trials(self.study)
            c = counts(self.study)
            step = next_step(c, self.config.n_trials)
            if step == "run":
                # seeded by the number a new trial gets now (a queued trial keeps its parameters)
                self.counted = sum(c.values())
                self.study.sampler = make_sampler(self.config, self.counted)
                self.current, self.lock_lost = None, False
                self.study.optimize(self.objective, n_trials=1, catch=(TorchcalError, RuntimeError, ValueError))
            return step
        finally:
            self.lock.release()

    def _last_failed(self) -> bool:
        from optuna.trial import TrialState

        if self.current is None:
            return False
        trial = next((t for t in self.study.get_trials(deepcopy=False) if t.number == self.current), None)
        return trial is not None and trial.state == TrialState.FAIL

    def _failed_in_database(self) -> bool:
        """``_last_failed``, read after an error: a database still away counts as yes (the next
        step meets it again and waits for it)."""
        try:
            return self._last_failed()
        except Exception as exc:
            if _database_cause(exc) is None:
                raise
            return True

    def run(self) -> int:
        """Trials this worker ran before the budget was met."""
        _quiet_heartbeat_errors()
        _one_line_trial_failures()
        ran, failures, lost_since = 0, 0, None
        while True:
            try:
                step = self._step()
                # a trial given up for a lost lock says nothing about the configurations
                failed = step == "run" and not self.lock_lost and self._last_failed()
                lost_since = None
            except Exception as exc:
                if _taken_over(exc) and self._failed_in_database():
                    # this worker's trial lost its heartbeat (a database outage) and another worker
                    # failed and queued it again; the queued copy runs like any retry
                    print(f"study '{self.config.name}': trial {self.current} was taken over after its heartbeat was "
                          "lost", file=sys.stderr)
                    continue
                lost = _database_cause(exc)
                if lost is None:
                    raise
                now = time.monotonic()
                lost_since = lost_since or now
                if now - lost_since > self.config.reconnect_s:
                    raise TorchcalError(f"study '{self.config.name}': lost the database at {shown_url(self.url)} for "
                                        f"{self.config.reconnect_s:g} s ({_first_line(lost)}); run the command again to "
                                        "resume") from None
                time.sleep(1.0)
                continue
            if step == "stop":
                return ran
            if step == "wait":
                time.sleep(self.config.heartbeat_interval_s)
                continue
            ran += 1
            failures = failures + 1 if failed else 0
            if failures >= MAX_CONSECUTIVE_FAILURES:
                raise TorchcalError(f"study '{self.config.name}': {failures} trials in a row failed; see the failed "
                                    "trials' messages")


def work(base, config: StudyConfig, study_dir: str, threads: int = 1) -> int:
    """Entry point of a worker process: returns the trials it ran."""
    import optuna
    import torch

    torch.set_num_threads(max(1, threads))
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    if base.fit.jobs is None:  # the study's workers are its parallelism: each trial fits in its own process
        base = replace(base, fit=replace(base.fit, jobs=1))
    return Worker(base, config, Path(study_dir)).run()
