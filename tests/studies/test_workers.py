"""Several workers share one study: every trial runs once, none is lost, the budget is kept exactly."""

from __future__ import annotations

import uuid

import pytest
from optuna.trial import TrialState
from study_procs import assert_budget_kept, finish, load, start, study_command

N_TRIALS = 8


def _check_shared(trials, n_workers: int) -> set[int]:
    numbers = [t.number for t in trials]
    assert len(numbers) == len(set(numbers))
    # the study lock makes "is there room, take a trial" one step: never a trial past the budget,
    # and the workers' sampler streams differ (a float parameter: equal only if drawn twice)
    assert_budget_kept(trials, N_TRIALS)
    assert len(trials) == N_TRIALS
    assert not [t for t in trials if t.state == TrialState.FAIL]
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
    assert first.params == {"fit.residual_hidden": 40, "fit.mayfly_population": 8, "fit.residual_margin": 0.05}
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


def test_trial_seeds_depend_on_the_trial_number_only(tmp_path):
    """Every new trial has its own sampler stream, whichever worker or restart draws it."""
    from torchcal.studies.spec import StudyConfig
    from torchcal.studies.storage import trial_seed

    config = StudyConfig(seed=3)
    seeds = [trial_seed(config, k) for k in range(50)]
    assert len(set(seeds)) == 50 and seeds == [trial_seed(StudyConfig(seed=3), k) for k in range(50)]
    assert trial_seed(StudyConfig(seed=4), 0) != seeds[0]
