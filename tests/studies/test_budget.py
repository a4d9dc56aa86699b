"""The budget as the database counts it: queued trials are run, repeats are not re-evaluated, seeds.

In-process studies on SQLite with a small twin; the pieces the multi-process tests rely on.
"""

from __future__ import annotations

import optuna
import pytest
from optuna.trial import TrialState

from torchcal.config import compose_run_config
from torchcal.studies.runner import run_study
from torchcal.studies.spec import StudyConfig
from torchcal.studies.storage import open_study, trial_seed
from torchcal.studies.worker import next_step

pytestmark = pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning")
MARGIN = {"fit.residual_margin": {"type": "float", "low": 0.03, "high": 0.08}}


def _base(tmp_path):
    base, _ = compose_run_config(["measurement=twin_small", "experiment=quick", "twin.n_train=200", "twin.n_test=80",
                                  "fit.residual=elm", "fit.residual_hidden=20", f"out={tmp_path / 'runs'}",
                                  "fit.progress=false", "fit.gravity_compliance=wrist", "fit.joint_harmonics=none"])
    return base


def _study(name: str, n: int, space=None, **kw) -> StudyConfig:
    kw = {"sampler": "random", "heartbeat_interval_s": 1, "grace_period_s": 3, **kw}
    return StudyConfig(name=name, n_trials=n, refit_best=False, search_space=space or MARGIN, **kw)


def _trials(outcome, name):
    return optuna.load_study(study_name=name, storage=outcome.storage).get_trials()


def test_next_step_counts_a_queued_trial_as_a_slot_to_fill():
    base = {"COMPLETE": 0, "PRUNED": 0, "FAIL": 0, "RUNNING": 0, "WAITING": 0}
    # the state: 7 finished, the killed trial failed and queued again -> run it
    assert next_step({**base, "COMPLETE": 5, "PRUNED": 2, "FAIL": 1, "WAITING": 1}, 8) == "run"
    # the last slot is held by a running trial: wait for it to finish or go stale
    assert next_step({**base, "COMPLETE": 7, "RUNNING": 1}, 8) == "wait"
    assert next_step({**base, "COMPLETE": 7, "RUNNING": 1, "WAITING": 1}, 8) == "wait"
    assert next_step({**base, "COMPLETE": 6, "PRUNED": 2, "FAIL": 3}, 8) == "stop"


def test_a_queued_retry_in_a_full_budget_is_run(tmp_path):
    """The issue's dead end: finished + queued = budget. The queued copy must run, and nothing else."""
    base = _base(tmp_path)
    config = _study("queued", 3)
    first = run_study(base, _study("queued", 2))
    study = open_study(config, first.study_dir)
    done = study.get_trials()
    # what the retry callback writes for a killed trial: a FAIL and a WAITING copy of its parameters
    study.add_trial(optuna.create_trial(state=TrialState.FAIL, params={"fit.residual_margin": 0.0456},
                                        distributions=done[0].distributions))
    study.add_trial(optuna.create_trial(state=TrialState.WAITING, params={"fit.residual_margin": 0.0456},
                                        distributions=done[0].distributions, system_attrs={"failed_trial": 2}))
    outcome = run_study(base, config)
    trials = _trials(outcome, "queued")
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 2 + [TrialState.FAIL, TrialState.COMPLETE]
    assert trials[3].params == {"fit.residual_margin": 0.0456} and trials[3].values[0] > 0
    assert outcome.short_by == 0 and "WARNING" not in outcome.summary("queued")


def test_summary_warns_when_the_study_ends_short(tmp_path):
    """A trial still running elsewhere when the command ends: the last line says so, with the database's counts."""
    from torchcal.studies.runner import StudyOutcome

    c = {"COMPLETE": 5, "PRUNED": 2, "FAIL": 1, "RUNNING": 0, "WAITING": 1}
    line = StudyOutcome(tmp_path, "sqlite://", c, 8, 3, None, None).summary("s")
    assert "7 of 8 trials finished (5 complete, 2 pruned); 1 failed, 0 running, 1 waiting" in line
    assert "WARNING: 1 trial(s) short of the budget" in line


def test_resume_draws_new_configurations(tmp_path):
    """A resumed study does not restart its sampler's stream (a float parameter: equal only if redrawn)."""
    base = _base(tmp_path)
    run_study(base, _study("resume", 2))
    outcome = run_study(base, _study("resume", 4))
    trials = _trials(outcome, "resume")
    margins = [t.params["fit.residual_margin"] for t in trials]
    assert len(trials) == 4 and len(set(margins)) == 4
    # and each new trial's draw is the one its number seeds, whatever process drew it
    fresh = optuna.samplers.RandomSampler(seed=trial_seed(_study("resume", 4), 3))
    dist = trials[3].distributions["fit.residual_margin"]
    assert fresh.sample_independent(None, None, "fit.residual_margin", dist) == margins[3]


def test_a_repeated_configuration_reuses_the_result(tmp_path):
    """Two choices, five trials: the sampler must propose a scored configuration again; it is not refitted."""
    base = _base(tmp_path)
    space = {"fit.residual_hidden": {"type": "categorical", "choices": [10, 20]}}
    outcome = run_study(base, _study("repeat", 5, space))
    trials = _trials(outcome, "repeat")
    repeats = [t for t in trials if "repeat_of" in t.user_attrs]
    assert len(trials) == 5 and len(repeats) >= 3
    for t in repeats:
        original = trials[t.user_attrs["repeat_of"]]
        assert original.params == t.params and original.values == t.values and "repeat_of" not in original.user_attrs
        assert not (outcome.study_dir / "trials" / f"{t.number:04d}").exists()
    evaluated = [t for t in trials if "repeat_of" not in t.user_attrs]
    assert len({t.params["fit.residual_hidden"] for t in evaluated}) == len(evaluated)


def test_one_worker_study_repeats(tmp_path):
    """The same one-worker study twice (TPE, fixed seed): identical parameters and values in both databases."""
    space = {**MARGIN, "fit.residual_hidden": {"type": "int", "low": 10, "high": 40, "step": 10}}
    runs = []
    for k in range(2):
        base = _base(tmp_path / str(k))
        outcome = run_study(base, _study("again", 5, space, sampler="tpe", seed=4))
        runs.append([(t.number, t.state, t.params, t.values) for t in _trials(outcome, "again")])
    assert runs[0] == runs[1]
    assert len({tuple(sorted(p.items())) for _, _, p, _ in runs[0]}) == 5


def test_a_trial_killed_before_its_first_heartbeat_is_retried(tmp_path):
    """Taken (RUNNING) but no heartbeat ever written: failed after the grace period and queued again."""
    import time

    config = _study("silent", 2, grace_period_s=2)
    study = open_study(config, tmp_path)
    orphan = study.ask()  # what a worker killed right after taking a trial leaves behind
    orphan.suggest_float("fit.residual_margin", 0.03, 0.08)
    optuna.storages.fail_stale_trials(study)
    assert study.get_trials()[0].state == TrialState.RUNNING  # a live trial's first heartbeat may be on its way
    time.sleep(2.5)
    optuna.storages.fail_stale_trials(study)
    trials = study.get_trials()
    assert [t.state for t in trials] == [TrialState.FAIL, TrialState.WAITING]
    assert trials[1].params == trials[0].params


def test_a_trial_failed_by_another_worker_is_left_to_its_retry(tmp_path):
    """A worker whose heartbeat was lost (a database outage) finds its trial failed and queued again
    by another worker: it goes on, the queued copy is run, and the budget is met."""
    from optuna.storages import RetryHeartbeatStaleTrialCallback

    from torchcal.studies.worker import Worker

    config = _study("taken", 2)
    worker = Worker(_base(tmp_path), config, tmp_path)
    real, taken = worker.objective, []

    def objective(trial):
        value = real(trial)
        if not taken:  # what the other worker's fail_stale_trials does to this trial
            taken.append(trial.number)
            other = open_study(config, tmp_path)
            other._storage.set_trial_state_values(trial._trial_id, TrialState.FAIL)
            RetryHeartbeatStaleTrialCallback(max_retry=1)(other, other._storage.get_trial(trial._trial_id))
        return value

    worker.objective = objective
    worker.run()
    trials = open_study(config, tmp_path).get_trials()
    assert trials[taken[0]].state == TrialState.FAIL
    retries = [t for t in trials if RetryHeartbeatStaleTrialCallback.retried_trial_number(t) == taken[0]]
    assert len(retries) == 1 and retries[0].state == TrialState.COMPLETE
    assert retries[0].params == trials[taken[0]].params
    assert sum(t.state == TrialState.COMPLETE for t in trials) == 2


def test_a_study_is_not_resumed_with_another_search_space(tmp_path):
    """Trials of two questions never mix: the same name with another space is refused before any trial."""
    from torchcal.core.errors import TorchcalError

    base = _base(tmp_path)
    first = run_study(base, _study("space", 1))
    other = {"fit.residual_hidden": {"type": "int", "low": 10, "high": 30}}
    with pytest.raises(TorchcalError, match="another search space"):
        run_study(base, _study("space", 2, space=other))
    assert len(_trials(first, "space")) == 1


def test_a_new_trial_taken_after_the_lock_was_lost_is_given_up(tmp_path):
    """A server restart can end the lock's session mid-step: another worker may then read the same
    counts and seed its sampler alike. The new trial is failed before it draws parameters, and the
    budget is met by trials drawn afterwards, each configuration once."""
    from torchcal.studies.worker import Worker

    config = _study("lost", 2)
    worker = Worker(_base(tmp_path), config, tmp_path)
    held, answers = worker.lock.held, [False]
    worker.lock.held = lambda: answers.pop() if answers else held()
    assert worker.run() == 3
    trials = open_study(config, tmp_path).get_trials()
    assert [t.state for t in trials] == [TrialState.FAIL, TrialState.COMPLETE, TrialState.COMPLETE]
    assert trials[0].params == {}
    assert trials[1].params != trials[2].params
