"""A study survives SIGKILL: finished trials kept, the killed one failed and retried; both storages."""

from __future__ import annotations

import uuid

import pytest
from optuna.storages import RetryHeartbeatStaleTrialCallback
from optuna.trial import TrialState
from study_procs import (
    assert_budget_kept,
    finish,
    kill_during_second_trial,
    load,
    make_heartbeat_stale,
    start,
    study_command,
)

N_TRIALS = 5
pytestmark = pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning")


def _states(trials) -> str:
    return "\n".join(f"{t.number} {t.state.name} {t.system_attrs} {t.user_attrs}" for t in trials)


def _kill_and_resume(tmp_path, name: str, storage: str, stale: bool = True) -> None:
    first = start(study_command(name, N_TRIALS, storage), tmp_path)
    killed = kill_during_second_trial(first, name, storage)
    before = {t.number: (t.state, t.values, t.params) for t in load(name, storage).trials if t.state.is_finished()}
    # stale: the command restarts past the grace period (its last heartbeat dated back as the clock
    # would have moved it) and fails and retries the trial at once; fresh: restarted at once, the
    # command waits for the heartbeat to go stale before retrying it
    if stale:
        make_heartbeat_stale(name, storage, killed)
    out = finish(start(study_command(name, N_TRIALS, storage), tmp_path))
    assert f"{N_TRIALS} of {N_TRIALS} trials finished" in out.strip().splitlines()[-1]

    trials = load(name, storage).trials
    by_number = {t.number: t for t in trials}
    # nothing finished before the kill is lost or changed
    for number, (state, values, params) in before.items():
        t = by_number[number]
        assert (t.state, t.values, t.params) == (state, values, params)
    # the killed trial is failed, and retried once with the same parameters
    assert by_number[killed].state == TrialState.FAIL
    retries = [t for t in trials if RetryHeartbeatStaleTrialCallback.retried_trial_number(t) == killed]
    assert len(retries) == 1, _states(trials)
    # the retry starts from what the killed trial had suggested when it died (a kill between two
    # suggest calls leaves only the first; the retry suggests the rest itself)
    known = by_number[killed].params
    assert {k: retries[0].params[k] for k in known} == known and retries[0].state.is_finished()
    assert_budget_kept(trials, N_TRIALS)


@pytest.mark.slow
@pytest.mark.parametrize("stale", [False, True], ids=["inside-grace", "outside-grace"])
def test_kill_and_resume_sqlite(tmp_path, stale):
    name = "resume"
    storage = f"sqlite:///{tmp_path / 'runs' / 'studies' / name / 'study.db'}"
    _kill_and_resume(tmp_path, name, storage, stale)


@pytest.mark.slow
@pytest.mark.postgres
def test_kill_and_resume_postgres(tmp_path, postgres_url):
    _kill_and_resume(tmp_path, f"resume-{uuid.uuid4().hex[:8]}", postgres_url)
