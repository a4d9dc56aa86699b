"""Faults on a shared PostgreSQL study: a worker killed mid-trial while another runs, the server restarted.

The outage tests stop a server of their own (``private_postgres``): the shared one serves tests
running beside them on the other pytest worker.

Each test ends by reading the database: exactly the budget of finished trials, none WAITING or
RUNNING, and no configuration evaluated twice (trials sample a float, so only a repeated sampler
stream or a re-run trial could give two equal configurations).
"""

from __future__ import annotations

import time
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

N_TRIALS = 6
pytestmark = [pytest.mark.slow, pytest.mark.postgres,
              pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning")]


def _two_workers(tmp_path, name: str, url: str, *extra: str):
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
    a = start(study_command(name, N_TRIALS, url, 1, *extra), tmp_path / "a")
    b = start(study_command(name, N_TRIALS, url, 1, *extra), tmp_path / "b")
    return a, b


@pytest.mark.parametrize("stale", [False, True], ids=["inside-grace", "outside-grace"])
def test_worker_killed_mid_trial_while_another_runs(tmp_path, postgres_url, stale):
    name = f"kill-{uuid.uuid4().hex[:8]}"
    a, b = _two_workers(tmp_path, name, postgres_url)
    killed = kill_during_second_trial(a, name, postgres_url)
    killed_params = load(name, postgres_url).trials[killed].params
    if stale:  # restarted past the grace period: the killed trial's last heartbeat is stale (see make_heartbeat_stale)
        make_heartbeat_stale(name, postgres_url, killed)
    out_a = finish(start(study_command(name, N_TRIALS, postgres_url), tmp_path / "a"))
    out_b = finish(b)

    trials = load(name, postgres_url).trials
    assert_budget_kept(trials, N_TRIALS)
    # the killed trial was failed once its heartbeat went stale, queued again and finished by a live worker
    assert trials[killed].state == TrialState.FAIL
    retries = [t for t in trials if RetryHeartbeatStaleTrialCallback.retried_trial_number(t) == killed]
    assert len(retries) == 1 and retries[0].state.is_finished()
    assert {k: retries[0].params[k] for k in killed_params} == killed_params
    for out in (out_a, out_b):
        last = out.strip().splitlines()[-1]
        assert f"{N_TRIALS} of {N_TRIALS} trials finished" in last and "0 running, 0 waiting" in last
        assert "WARNING" not in last and "Traceback" not in out


def _wait_finished(name: str, url: str, n: int, timeout: float = 300) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if sum(t.state.is_finished() for t in load(name, url).get_trials(deepcopy=False)) >= n:
                return
        except Exception:  # noqa: BLE001 (the study is not created yet; optuna and the storage raise their own kinds)
            pass
        time.sleep(0.2)
    pytest.fail("no trial finished")


def test_server_restarted_mid_study(tmp_path, private_postgres):
    """Workers ride out a short outage: they reconnect and the study ends complete."""
    name, url = f"restart-{uuid.uuid4().hex[:8]}", private_postgres.url
    a, b = _two_workers(tmp_path, name, url)
    _wait_finished(name, url, 1)
    private_postgres.control("restart")
    out = [finish(a), finish(b)]
    assert_budget_kept(load(name, url).trials, N_TRIALS)
    assert all("Traceback" not in o for o in out), out


def test_server_gone_longer_than_reconnect(tmp_path, private_postgres):
    """A server that stays away: each worker stops with one line; the next run finishes the study."""
    name, url = f"gone-{uuid.uuid4().hex[:8]}", private_postgres.url
    # a reconnect period of 1 s: the workers give up about 2 s after the server went (with 3 s, about 4 s)
    a, b = _two_workers(tmp_path, name, url, "study.reconnect_s=1")
    _wait_finished(name, url, 1)
    private_postgres.control("stop")
    try:
        outs = [p.communicate(timeout=120)[0] for p in (a, b)]
    finally:
        private_postgres.control("start")
    for p, out in zip((a, b), outs):
        if p.returncode == 0:  # it had finished its part before the server went
            continue
        assert p.returncode == 2, out
        assert "Traceback" not in out, out
        assert out.strip().splitlines()[-1].startswith("torchcal: error: study") and "lost the database" in out
    finish(start(study_command(name, N_TRIALS, url), tmp_path / "a"))
    assert_budget_kept(load(name, url).trials, N_TRIALS)
