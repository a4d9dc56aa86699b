"""A study-wide lock around "how many trials are left, and take one".

Workers of one study decide whether to start a trial from the counts in the database, then take
it (Optuna pops a queued trial or creates a new one). Without a lock two workers can read the same
counts and both take the last trial of the budget, or both go for one queued retry so that one of
them creates a fresh trial past the budget. The lock makes the decision and the taking one step:

* PostgreSQL: a session-level advisory lock (``pg_advisory_lock``) keyed by the study name, held
  on a connection of its own. The server releases it when that connection ends, so a worker killed
  while holding it (SIGKILL, a lost machine) blocks no one.
* SQLite (one machine): ``flock`` on ``<database>.lock`` beside the database file; the kernel
  releases it when the process dies.
* Other database servers: no lock; two workers may then finish a trial more than the budget.

A server restart ends every session, and with it an advisory lock its holder still thinks it has:
another worker can then take the lock and read the same counts. :meth:`StudyLock.held` tells the
holder, once its trial is taken, whether the lock lasted through the step (the worker then gives a
new trial up rather than run a configuration another worker may be running too).
"""

from __future__ import annotations

import contextlib
import hashlib
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

if TYPE_CHECKING:
    from sqlalchemy.engine import Connection, Engine


def _key(name: str) -> int:
    """A signed 64-bit advisory-lock key for a study name."""
    return int.from_bytes(hashlib.sha256(f"torchcal-study:{name}".encode()).digest()[:8], "big", signed=True)


class StudyLock:
    """Re-entrant-free mutual exclusion between the workers of one study (see the module docstring)."""

    def __init__(self, url: str, study_name: str, study_dir: Path) -> None:
        self.url, self.name = url, study_name
        self._file: TextIO | None = None
        self._engine: Engine | None = None
        self._conn: Connection | None = None
        self._path: Path | None = None  # the lock file (SQLite only)
        if url.startswith("sqlite"):
            from sqlalchemy.engine import make_url

            database = make_url(url).database
            if not database or database == ":memory:":  # in memory: no database file to sit beside
                self._path = Path(study_dir) / ".study.lock"
            else:
                self._path = Path(database + ".lock")

    @property
    def kind(self) -> str:
        if self._path is not None:
            return "file"
        return "advisory" if self.url.startswith("postgresql") else "none"

    def acquire(self) -> None:
        """Block until this worker holds the lock."""
        if self._path is not None:  # kind "file"
            import fcntl

            self._path.parent.mkdir(parents=True, exist_ok=True)
            # the flock lives with this open file, so it stays open until release() closes it
            self._file = open(self._path, "a+")  # noqa: SIM115
            fcntl.flock(self._file, fcntl.LOCK_EX)
        elif self.kind == "advisory":
            import sqlalchemy

            if self._engine is None:
                from torchcal.studies.storage import connect_args

                self._engine = sqlalchemy.create_engine(self.url, pool_pre_ping=True, poolclass=sqlalchemy.pool.NullPool,
                                                        connect_args=connect_args(self.url))
            conn = self._conn = self._engine.connect()
            try:
                conn.execute(sqlalchemy.text("SELECT pg_advisory_lock(:k)"), {"k": _key(self.name)})
                conn.commit()
            except BaseException:
                self._close_conn()
                raise

    def held(self) -> bool:
        """Whether this worker still holds the lock it acquired (an advisory lock dies with its session).

        A file lock lasts as long as its open file, so it is held between ``acquire`` and ``release``;
        with no lock (other servers) there is nothing to lose.
        """
        if self._path is not None:
            return self._file is not None
        if self.kind != "advisory":
            return True
        if self._conn is None:
            return False
        import sqlalchemy
        from sqlalchemy.exc import SQLAlchemyError

        try:
            rows = self._conn.execute(sqlalchemy.text(
                "SELECT count(*) FROM pg_locks WHERE locktype = 'advisory' AND granted AND pid = pg_backend_pid()"))
            return bool(rows.scalar())
        except SQLAlchemyError:  # the session is gone (a server restart, a terminated backend)
            return False

    def release(self) -> None:
        """Give the lock up (idempotent; a lost connection has released it already)."""
        if self._file is not None:
            import fcntl

            fcntl.flock(self._file, fcntl.LOCK_UN)
            self._file.close()
            self._file = None
        if self._conn is not None:
            import sqlalchemy
            from sqlalchemy.exc import SQLAlchemyError

            try:
                self._conn.execute(sqlalchemy.text("SELECT pg_advisory_unlock(:k)"), {"k": _key(self.name)})
                self._conn.commit()
            except SQLAlchemyError:
                pass  # the connection is gone, and the server dropped the lock with it
            self._close_conn()

    def _close_conn(self) -> None:
        from sqlalchemy.exc import SQLAlchemyError

        if self._conn is not None:
            with contextlib.suppress(SQLAlchemyError):
                self._conn.close()
        self._conn = None

    def __enter__(self) -> StudyLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()
