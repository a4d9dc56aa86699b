"""Helpers to run ``torchcal study`` as separate processes, as users and cluster workers do."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import optuna
import pytest

REPO = Path(__file__).resolve().parents[2]

HEARTBEAT_S, GRACE_S = 1, 6  # the study options below: a killed trial is stale 6 s after its last heartbeat

# A study small enough for CI: a 300-pose twin, Mayfly with 10 iterations, trials of about a second.
# The float margin makes an exact repeat of a configuration a repeated sampler stream, not chance.
# The joint-space structure is given, not cross-validated among seven options with the blocks check
# after it: the fixed part every study process fits before its first trial (these tests test budget,
# faults, resume and locks, not the structure choice) takes about 1 s less CPU per study process.
SMALL = [
    "study=elm_mayfly",
    "measurement=twin_small",
    "experiment=quick",
    "twin.n_train=200",
    "twin.n_test=100",
    "fit.mayfly_iterations=10",
    "study.search_space={fit.residual_hidden: {type: int, low: 20, high: 60, step: 10}, "
    "fit.mayfly_population: {type: int, low: 6, high: 12, step: 2}, fit.residual_margin: {type: float, low: 0.03, high: 0.08}}",
    "fit.residual_hidden=40",
    "fit.mayfly_population=8",
    "fit.gravity_compliance=elbow+wrist",
    "fit.joint_harmonics=first",
    "fit.head_time_check=false",
    f"study.heartbeat_interval_s={HEARTBEAT_S}",
    f"study.grace_period_s={GRACE_S}",
    "study.refit_best=false",
]


def study_command(name: str, n_trials: int, storage: str | None = None, workers: int = 1, *extra: str) -> list[str]:
    cmd = [sys.executable, "-m", "torchcal.cli", "study", *SMALL, f"study.name={name}", f"study.n_trials={n_trials}",
           "--workers", str(workers), *extra]
    if storage:
        cmd += ["--storage", storage]
    return cmd


def start(cmd: list[str], cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "TORCHCAL_CONFIG_DIR": str(REPO / "configs"), "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def finish(proc: subprocess.Popen, timeout: float = 400) -> str:
    out, _ = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, out
    return out


def url(storage: str) -> str:
    """``storage`` with the driver the study command would use."""
    from torchcal.studies.spec import StudyConfig
    from torchcal.studies.storage import storage_url

    return storage_url(StudyConfig(storage=storage), Path("."))


def load(name: str, storage: str) -> optuna.Study:
    return optuna.load_study(study_name=name, storage=url(storage))


def evaluated_twice(trials) -> list[int]:
    """Numbers of complete trials that evaluated a configuration an earlier complete trial had evaluated."""
    from torchcal.studies.objective import same_configuration

    done = sorted((t for t in trials if t.state == optuna.trial.TrialState.COMPLETE and "repeat_of" not in t.user_attrs),
                  key=lambda t: t.number)
    return [t.number for k, t in enumerate(done) if any(same_configuration(t, o) for o in done[:k])]


def assert_budget_kept(trials, n_trials: int) -> None:
    """Exactly ``n_trials`` finished, none queued or running, nothing evaluated twice."""
    from optuna.trial import TrialState

    states = [t.state for t in trials]
    assert sum(s in (TrialState.COMPLETE, TrialState.PRUNED) for s in states) == n_trials, states
    assert TrialState.WAITING not in states and TrialState.RUNNING not in states, states
    assert evaluated_twice(trials) == []


def kill_during_second_trial(proc: subprocess.Popen, name: str, storage: str, timeout: float = 300) -> int:
    """SIGKILL the study's process group once a trial has finished and one of its own is running.

    Trials take about a second: one read as running near its end can finish in the moment between the
    read and the kill. Then nothing is left to test, and the test is skipped, saying so.
    """
    deadline = time.monotonic() + timeout
    study = None  # opened once: opening a storage costs far more than a read of its trials (tens of ms to a
    # second under load), long enough to miss a whole trial of about a second between two reads
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail("the study finished before it could be killed:\n" + proc.stdout.read())
        try:
            study = study or load(name, storage)
            trials = study.get_trials(deepcopy=False)
        except Exception:  # noqa: BLE001 (the study is not created yet; optuna and the storage raise their own kinds)
            trials = []
        done = [t for t in trials if t.state.is_finished()]
        # mid-trial: its parameters are drawn and the fit is under way
        running = [t for t in trials if t.state == optuna.trial.TrialState.RUNNING and t.params
                   and t.user_attrs.get("worker_pid") == proc.pid]
        if done and running:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            killed = load(name, storage).trials[running[0].number]
            if killed.state.is_finished():  # finished between the read and the kill: nothing left to test
                pytest.skip(f"trial {killed.number} finished before the kill landed ({killed.state.name})")
            return running[0].number
        time.sleep(0.05)
    pytest.fail("no trial was seen running")


def make_heartbeat_stale(name: str, storage: str, number: int) -> None:
    """Date trial ``number``'s last heartbeat past the grace period, in the database.

    This is the state a command started more than ``GRACE_S`` after the trial's worker was killed
    finds (a dead worker writes no heartbeat), without waiting out the grace period. The storage's
    own stale-trial query (the one every worker runs before taking a trial) must list the trial.
    """
    from datetime import timedelta

    import sqlalchemy
    from optuna.storages import RDBStorage
    from optuna.storages._rdb import models
    from sqlalchemy import orm

    engine = sqlalchemy.create_engine(url(storage))
    try:
        with orm.Session(engine) as session, session.begin():
            trial = (session.query(models.TrialModel).join(models.StudyModel)
                     .filter(models.StudyModel.study_name == name, models.TrialModel.number == number).one())
            # the database's clock, as Optuna's heartbeats and its stale-trial query use it
            now = session.execute(sqlalchemy.func.now()).scalar().replace(tzinfo=None)
            beat = session.query(models.TrialHeartbeatModel).filter_by(trial_id=trial.trial_id).one_or_none()
            if beat is None:  # killed before its heartbeat thread's first write
                beat = models.TrialHeartbeatModel(trial_id=trial.trial_id)
                session.add(beat)
            beat.heartbeat = now - timedelta(seconds=GRACE_S + 2)
            trial_id, study_id = trial.trial_id, trial.study_id
    finally:
        engine.dispose()
    check = RDBStorage(url(storage), heartbeat_interval=HEARTBEAT_S, grace_period=GRACE_S)
    try:
        stale = trial_id in check._get_stale_trial_ids(study_id)
        # or a worker still running found it stale first and failed it (its own check before each trial)
        assert stale or check.get_trial(trial_id).state == optuna.trial.TrialState.FAIL
    finally:
        check.engine.dispose()


def open_storage_once(url: str) -> str:
    """Open (and so create) the study tables at ``url``; the error text if it failed."""
    from torchcal.core.errors import TorchcalError
    from torchcal.studies.spec import StudyConfig
    from torchcal.studies.storage import open_storage

    try:
        open_storage(StudyConfig(storage=url), Path("."))
        return ""
    except TorchcalError as exc:
        return str(exc)
