"""Several workers share one study: every trial runs once, none is lost, the budget is kept."""

from __future__ import annotations

import uuid

import pytest
from optuna.trial import TrialState
from study_procs import finish, load, start, study_command

N_TRIALS = 8


def _check_shared(trials, n_workers: int) -> set[int]:
    numbers = [t.number for t in trials]
    assert len(numbers) == len(set(numbers))
    finished = [t for t in trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]
    # both workers may start a last trial at the same instant: at most n_workers - 1 extra
    assert N_TRIALS <= len(finished) <= N_TRIALS + n_workers - 1
    # and they did not propose the same configurations in lock-step
    params = [tuple(sorted(t.params.items())) for t in sorted(finished, key=lambda t: t.number)]
    assert len(set(params)) > len(params) // 2
    assert not [t for t in trials if t.state in (TrialState.RUNNING, TrialState.WAITING, TrialState.FAIL)]
    # each trial folder holds its resolved config, written by the worker that ran it
    return {t.user_attrs["worker_pid"] for t in trials}


@pytest.mark.slow
@pytest.mark.postgres
def test_two_machines_one_postgres_study(tmp_path, postgres_url):
    """Two independent ``torchcal study`` processes (two machines) against one PostgreSQL study."""
    name = f"shared-{uuid.uuid4().hex[:8]}"
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = start(study_command(name, N_TRIALS, postgres_url), tmp_path / "a")
    b = start(study_command(name, N_TRIALS, postgres_url), tmp_path / "b")
    finish(a)
    finish(b)
    pids = _check_shared(load(name, postgres_url).trials, 2)
    assert len(pids) == 2, "both machines ran trials"


@pytest.mark.slow
def test_local_workers_sqlite(tmp_path):
    name = "local"
    out = finish(start(study_command(name, N_TRIALS, workers=2), tmp_path))
    storage = f"sqlite:///{tmp_path / 'runs' / 'studies' / name / 'study.db'}"
    trials = load(name, storage).trials
    _check_shared(trials, 2)
    assert (tmp_path / "runs" / "studies" / name / "report.md").is_file()
    assert "best trial" in out
    # the run configuration's own values are trial 0, so the study reports how the best compares with them
    first = min(trials, key=lambda t: t.number)
    assert first.user_attrs.get("default_configuration") is True
    assert first.params == {"fit.residual_hidden": 40, "fit.mayfly_population": 8}
    for t in trials:
        assert (tmp_path / "runs" / "studies" / name / "trials" / f"{t.number:04d}" / "config.yaml").is_file()


@pytest.mark.postgres
def test_workers_starting_together_on_an_empty_database(postgres_url):
    """Every worker creates Optuna's tables at start; on a fresh database only one can win the race."""
    import multiprocessing

    import psycopg
    from study_procs import open_storage_once

    name = f"torchcal_race_{uuid.uuid4().hex[:8]}"
    admin = postgres_url
    with psycopg.connect(admin.replace("+psycopg", ""), autocommit=True) as conn:
        conn.execute(f"CREATE DATABASE {name}")
    url = postgres_url.rsplit("/", 1)[0] + f"/{name}"
    try:
        with multiprocessing.get_context("spawn").Pool(4) as pool:
            errors = pool.map(open_storage_once, [url] * 4)
        assert errors == ["", "", "", ""]
    finally:
        with psycopg.connect(admin.replace("+psycopg", ""), autocommit=True) as conn:
            conn.execute(f"DROP DATABASE {name} WITH (FORCE)")


def test_local_workers_do_not_repeat_each_other(tmp_path):
    """Workers of one study draw from different sampler streams (same seed would mean same proposals)."""
    from torchcal.studies.spec import StudyConfig
    from torchcal.studies.storage import sampler_seed

    config = StudyConfig(seed=3)
    seeds = {sampler_seed(config, tmp_path, k) for k in range(4)}
    assert seeds == {3, 4, 5, 6}
