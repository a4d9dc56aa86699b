"""Bad study input is refused in one line before any trial: storages, workers, search spaces, resumes."""

from __future__ import annotations

import contextlib
import socket
import sqlite3
import threading
import time
from dataclasses import replace

import optuna
import pytest
from optuna.trial import TrialState

from torchcal.config import compose_run_config
from torchcal.core.errors import TorchcalError
from torchcal.studies import runner, storage
from torchcal.studies.objective import INTERRUPTED, RETRY_OF_INTERRUPTED
from torchcal.studies.runner import requeue_interrupted, run_study
from torchcal.studies.spec import Distribution, StudyConfig, check_space

pytestmark = pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning")
HIDDEN = {"fit.residual_hidden": {"type": "int", "low": 10, "high": 30}}


def _base(tmp_path, *extra):
    base, _ = compose_run_config(["measurement=twin_small", "experiment=quick", "twin.n_train=60", "twin.n_test=40",
                                  "fit.residual=elm", f"out={tmp_path / 'runs'}", "fit.progress=false",
                                  "fit.gravity_compliance=wrist", "fit.joint_harmonics=none", *extra])
    return base


def _study(name="s", n=1, space=None, **kw) -> StudyConfig:
    kw = {"sampler": "random", "heartbeat_interval_s": 1, "grace_period_s": 3, **kw}
    return StudyConfig(name=name, n_trials=n, refit_best=False, search_space=space or HIDDEN, **kw)


@pytest.mark.parametrize("url, message", [("sqlite:///", "in-memory"), ("sqlite://", "in-memory"),
                                          ("sqlite:///:memory:", "in-memory")])
def test_in_memory_storage_is_refused(tmp_path, url, message):
    with pytest.raises(TorchcalError, match=message):
        run_study(_base(tmp_path), _study(storage=url))
    assert not (tmp_path / "runs").exists()


def test_a_folder_as_storage_is_refused_and_nothing_is_created(tmp_path):
    folder = tmp_path / "sdir"
    with pytest.raises(TorchcalError, match="names a folder"):
        run_study(_base(tmp_path), _study(storage=f"sqlite:///{folder}/"))
    assert not folder.exists()
    folder.mkdir()
    with pytest.raises(TorchcalError, match="names a folder"):
        run_study(_base(tmp_path), _study(storage=f"sqlite:///{folder}"))
    assert folder.is_dir() and not any(folder.iterdir())


def test_another_applications_database_is_left_alone(tmp_path):
    path = tmp_path / "userapp.db"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE customers (id INTEGER)")
    conn.close()
    with pytest.raises(TorchcalError, match=r"another application's database.*customers"):
        run_study(_base(tmp_path), _study(storage=f"sqlite:///{path}"))
    with sqlite3.connect(path) as conn:
        tables = {n for (n,) in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    conn.close()
    assert tables == {"customers"}
    (tmp_path / "junk.db").write_text("not a database at all")
    with pytest.raises(TorchcalError, match="not an SQLite database"):
        storage.check_storage(f"sqlite:///{tmp_path / 'junk.db'}", configured=True)


def test_a_locked_study_database_is_announced_and_named_as_locked_not_as_foreign(tmp_path, monkeypatch):
    import sqlite3
    import warnings

    from torchcal.studies import storage

    path = tmp_path / "study.db"
    holder = sqlite3.connect(path, isolation_level=None)
    holder.execute("CREATE TABLE studies (study_id INTEGER)")
    assert not storage.sqlite_lock_held(path, wait_s=0.1)
    holder.execute("BEGIN EXCLUSIVE")  # another program holds the file
    try:
        assert storage.sqlite_lock_held(path, wait_s=0.1)
        monkeypatch.setattr(storage, "SQLITE_LOCK_WAIT_S", 0.2)
        monkeypatch.setattr(storage, "SQLITE_LOCK_PROBE_S", 0.1)
        with warnings.catch_warnings(record=True) as caught, pytest.raises(TorchcalError, match="still locked after 0 s"):
            warnings.simplefilter("always")
            storage.check_storage(f"sqlite:///{path}", configured=True)
        assert any("is locked by another process" in str(w.message) for w in caught)
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # released: no warning, no refusal
        storage.check_storage(f"sqlite:///{path}", configured=True)


def test_storage_inside_an_output_folder_is_refused(tmp_path):
    from torchcal.core.outputs import stamp_folder

    model = tmp_path / "model"
    model.mkdir()
    stamp_folder(model, "model")
    with pytest.raises(TorchcalError, match="--storage lies inside"):
        storage.check_storage(f"sqlite:///{model / 'study.db'}", configured=True)
    storage.check_storage(f"sqlite:///{tmp_path / 'study.db'}", configured=True)  # outside: fine


def test_an_unresponsive_server_fails_fast_naming_the_url(tmp_path, monkeypatch):
    """A server that accepts the connection and never answers: the connect timeout ends the wait."""
    pytest.importorskip("psycopg")
    monkeypatch.setattr(storage, "CONNECT_TIMEOUT_S", 1)
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    accepted = []
    stop = threading.Event()

    def accept() -> None:
        server.settimeout(0.2)
        while not stop.is_set():
            with contextlib.suppress(OSError):
                accepted.append(server.accept()[0])  # held open, never answered

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    port = server.getsockname()[1]
    started = time.monotonic()
    try:
        with pytest.raises(TorchcalError, match=rf"cannot open study storage '127.0.0.1:{port}/db'") as info:
            storage.open_storage(_study(storage=f"postgresql+psycopg://user:secret@127.0.0.1:{port}/db"), tmp_path)
    finally:
        stop.set()
        thread.join()
        for conn in accepted:
            conn.close()
        server.close()
    assert time.monotonic() - started < 30
    assert "secret" not in str(info.value) and "\n" not in str(info.value)


def test_workers_are_refused_or_capped(tmp_path):
    with pytest.raises(TorchcalError, match="at least 1"):
        run_study(_base(tmp_path), _study(), workers=0)
    with pytest.raises(TorchcalError, match=f"at most {runner.MAX_WORKERS} local workers"):
        run_study(_base(tmp_path), _study(), workers=runner.MAX_WORKERS + 1)
    assert not (tmp_path / "runs").exists()
    assert runner._workers(3, _study(n=5), 4, None) == 1  # one trial left: one worker
    assert runner._workers(2, _study(n=5), 0, None) == 2


@pytest.mark.parametrize(
    "space, message",
    [
        ({"fit.residul_hidden": {"type": "int", "low": 10, "high": 30}}, "did you mean 'fit.residual_hidden'"),
        ({"fit.residual_hidden": {"type": "float", "low": 10, "high": 30}}, "is an int option"),
        ({"fit.residual_margin": {"type": "float", "low": 0, "high": 0.5, "log": True}}, "log: true needs low > 0"),
        ({"fit.residual_hidden": {"type": "int", "low": 10, "high": 300, "step": -10}}, "step must be > 0"),
        ({"study.n_trials": {"type": "int", "low": 1, "high": 3}}, "fit.\\* or twin.\\* options"),
        ({"fit.residual": {"type": "categorical", "choices": ["elm", "bogus"]}}, "'bogus' is refused.*unknown residual"),
        ({"fit.residual_hidden": {"type": "int", "low": 10, "high": 50000}}, "50000 is refused"),
        ({"fit.head_time_check": {"type": "int", "low": 0, "high": 1}}, "true/false option"),
        ({"fit.residual_hidden": {"type": "int", "low": 10.5, "high": 30}}, "whole number"),
    ],
)
def test_bad_search_space_is_refused_before_any_trial(tmp_path, space, message):
    with pytest.raises(TorchcalError, match=message):
        run_study(_base(tmp_path), _study(space=space))
    assert not (tmp_path / "runs").exists()


def test_missing_data_file_is_refused(tmp_path):
    config = _study(robot=str(tmp_path / "robot.yaml"), train=str(tmp_path / "absent.csv"))
    (tmp_path / "robot.yaml").write_text("")
    with pytest.raises(TorchcalError, match=r"study\.train: no file"):
        check_space(_base(tmp_path), config)


def test_a_valid_space_passes():
    space = {"fit.residual": {"type": "categorical", "choices": ["elm", "mma-elm", "mlp"]},
             "fit.gravity_compliance": {"type": "categorical", "choices": ["auto", "none", "wrist"]},
             "fit.residual_margin": {"type": "float", "low": 0.01, "high": 0.1, "log": True}}
    base, _ = compose_run_config(["measurement=twin_small"])
    check_space(base, _study(space=space))
    assert Distribution.parse("k", {"type": "int", "low": 1, "high": 64, "log": True}).log


def test_resume_on_other_data_or_a_changed_case_is_refused(tmp_path):
    first = run_study(_base(tmp_path), _study("data"))
    with pytest.raises(TorchcalError, match=r"other data or options \(twin.n_train: 60 -> 70\)"):
        run_study(_base(tmp_path, "twin.n_train=70"), _study("data", 2))
    with pytest.raises(TorchcalError, match=r"fit\.residual_margin: 0\.05 -> 0\.07"):
        run_study(_base(tmp_path, "fit.residual_margin=0.07"), _study("data", 2))
    # a study recorded before an option existed: that option at its default changes nothing; set otherwise, it does
    stored = optuna.load_study(study_name="data", storage=first.storage)
    older = {k: v for k, v in stored.user_attrs["fingerprint"].items() if k != "fit.residual_margin"}
    stored.set_user_attr("fingerprint", older)
    with pytest.raises(TorchcalError, match=r"fit\.residual_margin: \(unset\) -> 0\.07"):
        run_study(_base(tmp_path, "fit.residual_margin=0.07"), _study("data", 1))
    runner._check_same_data(stored, _base(tmp_path), _study("data", 1))  # at its default: accepted
    (case,) = (first.study_dir / "cases").iterdir()
    with open(case / "train.csv", "a") as f:
        f.write("\n")
    with pytest.raises(TorchcalError, match=r"train\.csv changed"):
        run_study(_base(tmp_path), _study("data", 2))
    assert len(optuna.load_study(study_name="data", storage=first.storage).trials) == 1


def test_resume_on_changed_measured_files_is_refused(tmp_path):
    robot, train = tmp_path / "robot.yaml", tmp_path / "train.csv"
    robot.write_text("r")
    train.write_text("a")
    config = _study("files", robot=str(robot), train=str(train))
    before = runner.fingerprint(_base(tmp_path), config)
    train.write_text("b")
    after = runner.fingerprint(_base(tmp_path), config)
    assert before["study.train"] != after["study.train"] and before["study.robot"] == after["study.robot"]


def test_an_interrupted_trial_is_queued_again_once(tmp_path):
    """Ctrl-C fails the running trial; the next run of the command runs its parameters again."""
    study = optuna.create_study(storage=f"sqlite:///{tmp_path / 'i.db'}", study_name="i")
    study.enqueue_trial({"x": 3}, user_attrs={"default_configuration": True})

    def interrupted(trial):
        trial.suggest_int("x", 0, 5)
        from torchcal.studies.objective import StudyObjective

        objective = StudyObjective.__new__(StudyObjective)
        objective._run = lambda t: (_ for _ in ()).throw(KeyboardInterrupt)
        return StudyObjective.__call__(objective, trial)

    with pytest.raises(KeyboardInterrupt):
        study.optimize(interrupted, n_trials=1)
    (failed,) = study.get_trials()
    assert failed.state == TrialState.FAIL and failed.user_attrs[INTERRUPTED]
    assert requeue_interrupted(study) == [0]
    assert requeue_interrupted(study) == []  # once
    retry = study.get_trials()[1]
    assert retry.state == TrialState.WAITING and retry.user_attrs == {"default_configuration": True,
                                                                       RETRY_OF_INTERRUPTED: 0}
    study.optimize(lambda t: float(t.suggest_int("x", 0, 5)), n_trials=1)
    assert study.get_trials()[1].params == {"x": 3}
    # a retry of a retry stopped by Ctrl-C: a chain of max_retry retries stops
    with pytest.raises(KeyboardInterrupt):
        study.enqueue_trial({"x": 4}, user_attrs={RETRY_OF_INTERRUPTED: 1})
        study.optimize(interrupted, n_trials=1)
    assert requeue_interrupted(study, max_retry=1) == []
    assert requeue_interrupted(study, max_retry=3) == [2]  # it was the second retry of trial 0


@pytest.mark.parametrize("settings, message", [
    ({"objectives": ["validation_rms_mm", "validation_rms_mm"]}, "validation_rms_mm given twice"),
    ({"max_retry": -1}, "max_retry must be 0 or more"),
    ({"holdout_register": True}, "give study.holdout too"),
])
def test_settings_without_meaning_are_refused(settings, message):
    from torchcal.core.errors import TorchcalError
    from torchcal.studies.spec import StudyConfig

    config = StudyConfig(search_space={"fit.residual_hidden": {"type": "int", "low": 16, "high": 64}}, **settings)
    with pytest.raises(TorchcalError, match=message):
        config.validate()


@pytest.mark.parametrize("url, args", [
    ("postgresql+psycopg://u@h/db", {"connect_timeout": 10}),
    ("postgresql+pg8000://u@h/db", {"timeout": 10}),
    ("mysql+pymysql://u@h/db", {"connect_timeout": 10}),
    ("sqlite:////tmp/s.db", {}),
])
def test_each_driver_gets_its_own_connect_timeout(url, args):
    from torchcal.studies.storage import connect_args

    assert connect_args(url) == args


def test_a_best_refit_whose_export_is_its_run_folder_is_refused_before_any_trial(tmp_path):
    base = _base(tmp_path, f"export_dir={tmp_path / 'runs'}", "export=true")  # export_dir = out: the best's export is its run folder
    with pytest.raises(TorchcalError, match="give export_dir another place than out"):
        run_study(base, replace(_study("clash"), refit_best=True))
    assert not (tmp_path / "runs").exists()


def test_a_best_refit_whose_export_folder_cannot_be_written_is_refused_before_any_trial(tmp_path):
    blocker = tmp_path / "exports"
    blocker.write_text("a file where export_dir needs a folder")
    base = _base(tmp_path, f"export_dir={blocker}", "export=true")
    with pytest.raises(TorchcalError, match="a file stands where export_dir/studies/<study>/best needs a folder"):
        run_study(base, replace(_study("blocked"), refit_best=True))
    assert not (tmp_path / "runs").exists()  # refused before the study folder and its first trial
