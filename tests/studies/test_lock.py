"""The study lock: held while a worker decides, and known to be lost when its database session ends."""

from __future__ import annotations

import pytest

from torchcal.studies.lock import StudyLock, _key


def test_file_lock_is_held_between_acquire_and_release(tmp_path):
    lock = StudyLock(f"sqlite:///{tmp_path / 'study.db'}", "s", tmp_path)
    assert lock.kind == "file" and not lock.held()
    lock.acquire()
    assert lock.held()
    lock.release()
    assert not lock.held()


@pytest.mark.postgres
def test_advisory_lock_lost_with_its_session_is_reported_and_free_for_others(tmp_path, postgres_url):
    """What a server restart does to the holder: its session ends, and with it the lock."""
    import sqlalchemy

    from torchcal.studies.spec import StudyConfig
    from torchcal.studies.storage import storage_url

    url = storage_url(StudyConfig(storage=postgres_url), tmp_path)
    name = f"lock-{tmp_path.name}"
    lock = StudyLock(url, name, tmp_path)
    assert lock.kind == "advisory"
    lock.acquire()
    engine = sqlalchemy.create_engine(url, poolclass=sqlalchemy.pool.NullPool)
    key = _key(name) & 0xFFFFFFFFFFFFFFFF
    with engine.connect() as other:
        def try_lock() -> bool:
            return bool(other.execute(sqlalchemy.text("SELECT pg_try_advisory_lock(:k)"), {"k": _key(name)}).scalar())

        assert lock.held() and not try_lock()
        # end the holder's session as a restart would (the 64-bit key shows as two 32-bit halves)
        other.execute(sqlalchemy.text(
            "SELECT pg_terminate_backend(pid) FROM pg_locks WHERE locktype = 'advisory' AND classid = :hi "
            "AND objid = :lo AND objsubid = 1"), {"hi": key >> 32, "lo": key & 0xFFFFFFFF})
        assert not lock.held()
        assert try_lock()  # the server dropped it: another worker may now take it
        other.execute(sqlalchemy.text("SELECT pg_advisory_unlock_all()"))
    lock.release()  # a lost lock is released without an error
    engine.dispose()
