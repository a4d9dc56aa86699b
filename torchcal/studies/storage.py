"""Where a study lives: SQLite in its folder by default, any RDB URL for workers on many machines.

Heartbeats make a study survive a killed worker: every running trial records a heartbeat each
``heartbeat_interval_s``; before a worker takes a trial, Optuna fails any running trial whose
heartbeat is older than ``grace_period_s`` and the retry callback
(``RetryHeartbeatStaleTrialCallback``) queues it again (WAITING) with the same parameters; the
next trial any worker takes is that queued one. Finished trials are rows in the database and are
never touched again.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from torchcal.core.errors import TorchcalError
from torchcal.core.outputs import refuse_inside_output
from torchcal.studies.spec import StudyConfig

CREATE_ATTEMPTS = 5
#: seconds to wait for a database server to answer a new connection (a server that never answers
#: would otherwise hold the study for minutes, at the mercy of the system's TCP timeouts)
CONNECT_TIMEOUT_S = 10
#: seconds a study waits for its SQLite file's lock (local workers share the file and hold the lock
#: for milliseconds per write; longer means another program holds it)
SQLITE_LOCK_WAIT_S = 60.0
#: a lock still held after this long at opening is announced before the wait
SQLITE_LOCK_PROBE_S = 1.0


def storage_url(config: StudyConfig, study_dir: Path) -> str:
    """The study's storage URL: the configured one, or ``sqlite:///<study_dir>/study.db``.

    ``postgresql://`` without a driver means psycopg 3 (the ``postgres`` extra) when psycopg2,
    SQLAlchemy's default, is not installed.
    """
    if config.storage:
        url = config.storage
        if url.startswith("postgresql://"):
            import importlib.util

            if importlib.util.find_spec("psycopg2") is None and importlib.util.find_spec("psycopg") is not None:
                url = "postgresql+psycopg://" + url[len("postgresql://"):]
        return url
    return f"sqlite:///{(study_dir / 'study.db').resolve()}"


def connect_args(url: str) -> dict[str, Any]:
    """Driver arguments of a database server's connections: a connect timeout (PostgreSQL, MySQL)."""
    scheme = url.split("://", 1)[0]
    if scheme.endswith(("+pg8000", "+asyncpg")):  # these drivers name it "timeout"
        return {"timeout": CONNECT_TIMEOUT_S}
    if scheme.startswith(("postgresql", "mysql")):
        return {"connect_timeout": CONNECT_TIMEOUT_S}
    return {}


def shown_url(url: str) -> str:
    """``url`` without user and password, for messages."""
    return url.split("@")[-1] if "@" in url else url


def _optuna_tables() -> set[str]:
    """The tables Optuna's RDB storage creates (its heartbeats and Alembic's version table included)."""
    from optuna.storages._rdb import models

    return set(models.BaseModel.metadata.tables) | {"alembic_version"}


def check_storage(url: str, configured: bool) -> None:
    """Refuse a storage a study cannot live in before anything is created there.

    SQLite only: an in-memory database (lost when the command ends, and invisible to other
    workers), a path that ends in a separator or names a folder, a file that is not an SQLite
    database or holds another application's tables, and (``configured``, i.e. ``--storage``) a
    file inside a torchcal output folder, which a later run into that folder would delete.
    """
    if not url.startswith("sqlite"):
        return
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        database = make_url(url).database
    except ArgumentError as exc:
        raise TorchcalError(f"study storage '{url}': {exc}") from None
    query = make_url(url).query
    if not database or database == ":memory:" or database.startswith("file::memory:") or query.get("mode") == "memory":
        raise TorchcalError(f"study storage '{url}' is an in-memory database: a study must persist (its trials "
                            "are lost when the command ends); give a file, e.g. sqlite:///study.db")
    if database.endswith(("/", os.sep)) or Path(database).is_dir():
        raise TorchcalError(f"study storage '{url}' names a folder; give the database file, e.g. "
                            f"sqlite:///{database.rstrip('/' + os.sep)}/study.db")
    path = Path(database)
    if configured:
        refuse_inside_output(path.resolve(), "--storage", within=("study",))  # a study keeps its own in its folder
    if path.is_file() and path.stat().st_size > 0:
        import sqlite3

        _announce_lock(path)
        try:
            with sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True, timeout=SQLITE_LOCK_WAIT_S) as conn:
                tables = {name for (name,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            conn.close()
        except sqlite3.OperationalError as exc:
            if _is_lock_error(exc):
                raise TorchcalError(f"study storage '{url}': {path} is still locked after {SQLITE_LOCK_WAIT_S:.0f} s by "
                                    "another process; close the program that holds it open, or wait for it") from None
            raise TorchcalError(f"study storage '{url}': {path} is not an SQLite database ({exc})") from None
        except sqlite3.Error as exc:
            raise TorchcalError(f"study storage '{url}': {path} is not an SQLite database ({exc})") from None
        foreign = sorted(t for t in tables - _optuna_tables() if not t.startswith("sqlite_"))
        if foreign:
            shown = ", ".join(foreign[:5]) + (", ..." if len(foreign) > 5 else "")
            raise TorchcalError(f"study storage '{url}': {path} is another application's database (tables {shown}); "
                                "a study adds its tables only to its own database: give a new file")


def _is_lock_error(exc: Exception) -> bool:
    return "locked" in str(exc) or "busy" in str(exc)


def sqlite_lock_held(path: Path, wait_s: float = SQLITE_LOCK_PROBE_S) -> bool:
    """Whether another connection holds a write lock on the SQLite file ``path`` for longer than ``wait_s``."""
    import sqlite3

    conn = sqlite3.connect(str(path), timeout=wait_s, isolation_level=None)
    try:
        conn.execute("BEGIN IMMEDIATE")  # takes the write lock (released at once), waiting at most wait_s
        conn.execute("ROLLBACK")
        return False
    except sqlite3.OperationalError as exc:
        if _is_lock_error(exc):
            return True
        raise
    finally:
        conn.close()


def _announce_lock(path: Path) -> None:
    """Warn, before the wait, when the study's SQLite file is locked: the wait is otherwise silent."""
    import sqlite3
    import warnings

    try:
        held = sqlite_lock_held(path)
    except sqlite3.Error:  # not a database: check_storage says so next
        return
    if held:
        warnings.warn(f"study storage {path} is locked by another process (a program holding it open, or a worker "
                      f"writing); the study may wait up to {SQLITE_LOCK_WAIT_S:.0f} s for it", stacklevel=3)


def _storage_class():
    """Optuna's RDB storage, counting a trial that never wrote a heartbeat as stale too.

    Optuna finds stale trials by their last heartbeat only; a worker killed between taking a trial
    and its heartbeat thread's first write (milliseconds) would leave that trial RUNNING for good,
    and the workers waiting for it would wait for ever. Here such a trial is stale once this
    process has seen it RUNNING without any heartbeat for longer than the grace period (its own
    monotonic clock: no comparison of clocks between machines).
    """
    import time as _time

    import optuna
    from optuna.storages._rdb import models
    from optuna.trial import TrialState

    class Storage(optuna.storages.RDBStorage):
        _silent_since: dict[int, float]

        def _get_stale_trial_ids(self, study_id: int) -> list[int]:
            stale = super()._get_stale_trial_ids(study_id)
            # open_storage always passes a heartbeat interval, and Optuna looks for stale trials
            # only when heartbeats are enabled (its own _get_stale_trial_ids asserts the same)
            assert self.heartbeat_interval is not None
            grace = self.grace_period or 2 * self.heartbeat_interval
            with self.scoped_session() as session:
                silent = {i for (i,) in session.query(models.TrialModel.trial_id)
                          .outerjoin(models.TrialHeartbeatModel)
                          .filter(models.TrialModel.study_id == study_id,
                                  models.TrialModel.state == TrialState.RUNNING,
                                  models.TrialHeartbeatModel.trial_heartbeat_id.is_(None))}
            self.scoped_session.remove()
            now = _time.monotonic()
            seen = getattr(self, "_silent_since", {})
            self._silent_since = {i: seen.get(i, now) for i in silent}
            return stale + [i for i, since in self._silent_since.items() if now - since > grace and i not in stale]

    return Storage


def open_storage(config: StudyConfig, study_dir: Path, checked: bool = False):
    """An Optuna RDB storage with heartbeats and retry of stale trials (``checked``: the caller ran
    :func:`check_storage` on it already, as :func:`torchcal.studies.runner.run_study` does first)."""
    import warnings

    import optuna
    from sqlalchemy.exc import IntegrityError, ProgrammingError, SQLAlchemyError

    # Heartbeats are the documented way to recover killed trials; their "experimental" notice is noise.
    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    url = storage_url(config, study_dir)
    if not checked:
        check_storage(url, configured=bool(config.storage))
    if url.startswith("sqlite"):
        study_dir.mkdir(parents=True, exist_ok=True)
        # Several local workers share the file; wait for its lock instead of failing at once.
        engine_kwargs: dict[str, Any] = {"connect_args": {"timeout": SQLITE_LOCK_WAIT_S}}
    else:
        engine_kwargs = {"pool_pre_ping": True, "connect_args": connect_args(url)}
    # Workers on several machines may start together on an empty database: all of them try to
    # create Optuna's tables and all but one fail on the catalog's unique index. The tables then
    # exist, so opening again succeeds.
    error: Exception  # set before every break; the loop otherwise returns
    for attempt in range(CREATE_ATTEMPTS):
        try:
            return _storage_class()(
                url,
                engine_kwargs=engine_kwargs,
                heartbeat_interval=config.heartbeat_interval_s,
                grace_period=config.grace_period_s,
                heartbeat_stale_trial_callback=optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=config.max_retry),
            )
        except (IntegrityError, ProgrammingError) as exc:
            if attempt == CREATE_ATTEMPTS - 1:
                error = exc
                break
            time.sleep(0.5 * (attempt + 1))
        except (SQLAlchemyError, ImportError, ValueError, TypeError) as exc:
            error = exc
            break
    first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
    raise TorchcalError(f"cannot open study storage '{shown_url(url)}': {first}") from None


def trial_seed(config: StudyConfig, number: int) -> int:
    """The sampler seed of trial ``number``: a function of the study seed and the number only.

    A one-worker study thus draws the same trials every time; a resumed study, or several workers,
    draw every new trial from its own stream (a restarted worker reseeded with the study seed would
    propose the configurations it proposed before the restart again).
    """
    import numpy as np

    return int(np.random.SeedSequence([config.seed, number]).generate_state(1)[0] % (2**31))


def make_sampler(config: StudyConfig, number: int):
    """The sampler for the study's next new trial, ``number``."""
    import optuna

    seed = trial_seed(config, number)
    if config.sampler == "tpe":
        return optuna.samplers.TPESampler(seed=seed, n_startup_trials=min(8, max(2, config.n_trials // 3)))
    return optuna.samplers.RandomSampler(seed=seed)


def open_study(config: StudyConfig, study_dir: Path, checked: bool = False):
    """Create the study or load it when it exists (this is what makes a restart resume); ``checked``
    as for :func:`open_storage`."""
    import optuna

    storage = open_storage(config, study_dir, checked)
    try:
        return optuna.create_study(
            storage=storage,
            study_name=config.name,
            sampler=make_sampler(config, 0),
            pruner=optuna.pruners.NopPruner(),
            directions=config.directions,
            load_if_exists=True,
        )
    except ValueError as exc:  # e.g. an existing study with other directions
        raise TorchcalError(f"study '{config.name}': {exc}") from None
