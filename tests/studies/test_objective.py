"""In-process study pieces: search-space parsing, the objective's numbers, multi-objective report."""

from __future__ import annotations

import pytest

from torchcal.config import compose_run_config
from torchcal.core.errors import TorchcalError
from torchcal.studies.runner import run_study
from torchcal.studies.spec import Distribution, StudyConfig


def _small_base(tmp_path, **fit):
    # The joint-space structure is given, not cross-validated among seven options in every trial and
    # every check (a search space over fit.gravity_compliance still sets it per trial): these tests
    # test what a trial's value is, not the structure choice (as study_procs.SMALL).
    base, _ = compose_run_config(["measurement=twin_small", "experiment=quick", "twin.n_train=200", "twin.n_test=100",
                                  "fit.residual=elm", f"out={tmp_path / 'runs'}", "fit.progress=false",
                                  "fit.gravity_compliance=elbow+wrist", "fit.joint_harmonics=first",
                                  *[f"fit.{k}={v}" for k, v in fit.items()]])
    return base


@pytest.mark.parametrize(
    "spec, message",
    [
        ({"low": 1, "high": 2}, "needs a mapping with 'type'"),
        ({"type": "int", "low": 5, "high": 5}, "low < high"),
        ({"type": "categorical"}, "non-empty 'choices'"),
        ({"type": "uniform", "low": 0, "high": 1}, "type 'uniform' unknown"),
        ({"type": "int", "low": 0, "high": 3, "stride": 1}, "unknown fields"),
    ],
)
def test_bad_search_space_is_explained(spec, message):
    with pytest.raises(TorchcalError, match=message):
        Distribution.parse("fit.residual_hidden", spec)


def test_unknown_objective_and_empty_space_rejected():
    with pytest.raises(TorchcalError, match="objectives"):
        StudyConfig(objectives=["accuracy"], search_space={"fit.seed": {"type": "int", "low": 0, "high": 2}}).validate()
    with pytest.raises(TorchcalError, match="search_space is empty"):
        StudyConfig().validate()


def _fit_as_the_command_does(base, values: dict, train_csv, robot_yaml, folder):
    """``fit`` with the study's values, independently of the study: its kept model's CV RMS and folder."""
    import json

    from torchcal.data.measurements import load_measurements
    from torchcal.kinematics.robot import load_robot
    from torchcal.stages.geometry import fit_with_selection, save_fit, with_tool
    from torchcal.stages.residual import fit_residual_stage
    from torchcal.studies.objective import apply_values

    config = apply_values(base, values).fit
    robot = with_tool(load_robot(robot_yaml), config)
    train = load_measurements(train_csv, robot)
    result, structure = fit_with_selection(robot, train, config)
    save_fit(folder, robot, train, result, {})
    fit_residual_stage(folder, train, config, structure=structure)
    selection = json.loads((folder / "model_selection.json").read_text())
    return next(r["cv_rms_mm"] for r in selection["candidates"] if r["name"] == selection["chosen"])


@pytest.mark.slow
def test_objective_is_the_cv_rms_of_what_fit_keeps(tmp_path):
    """Each trial's value is the CV RMS that `fit` itself reports for the kept model with those settings."""
    import optuna

    base = _small_base(tmp_path, residual_hidden=20)
    study = StudyConfig(name="cv", n_trials=3, objectives=["validation_rms_mm", "model_size"], sampler="random",
                        refit_best=False,
                        search_space={"fit.gravity_compliance": {"type": "categorical", "choices": ["none", "wrist", "elbow+wrist"]}})
    outcome = run_study(base, study)
    trials = optuna.load_study(study_name="cv", storage=outcome.storage).trials
    assert len(trials) == 3 and all(t.state.name == "COMPLETE" for t in trials)
    case = next((outcome.study_dir / "cases").iterdir())
    for t in trials:
        if "repeat_of" in t.user_attrs:
            continue
        expected = _fit_as_the_command_does(base, t.params, case / "train.csv", case / "robot.yaml",
                                            tmp_path / f"fit{t.number}")
        assert t.values[0] == pytest.approx(expected, rel=1e-9)
        assert t.values[1] == t.user_attrs["model_size"]
        assert "regions" in t.user_attrs["cv_protocol"]
    values = {t.params["fit.gravity_compliance"]: t.values[0] for t in trials}
    if "none" in values and "wrist" in values:  # the twin sags under gravity: the term lowers the CV RMS
        assert values["wrist"] < values["none"]
    report = (outcome.study_dir / "report.md").read_text()
    assert "Pareto front" in report and (outcome.study_dir / "figures" / "tradeoff.png").is_file()


@pytest.mark.slow
def test_objective_on_a_held_out_series(tmp_path):
    """With study.holdout the value is `evaluate`'s RMS, on that file, of the model `fit` makes on train."""
    import optuna

    from torchcal.instruments.tracker.evaluate import evaluate
    from torchcal.instruments.tracker.twin_case import write_twin_case
    from torchcal.sim.twin import TwinConfig

    case = write_twin_case(tmp_path / "case", TwinConfig(seed=3, n_train=200, n_test=120, gravity=True, gear=True))
    base = _small_base(tmp_path)
    study = StudyConfig(name="held", n_trials=2, sampler="random", refit_best=True, robot=str(case["robot.yaml"]),
                        train=str(case["train.csv"]), holdout=str(case["test.csv"]), holdout_register=True,
                        search_space={"fit.gravity_compliance": {"type": "categorical", "choices": ["none", "wrist"]}})
    outcome = run_study(base, study)
    trials = optuna.load_study(study_name="held", storage=outcome.storage).trials
    for t in trials:
        if "repeat_of" in t.user_attrs:
            continue
        folder = tmp_path / f"fit{t.number}"
        _fit_as_the_command_does(base, t.params, case["train.csv"], case["robot.yaml"], folder)
        expected = evaluate(folder, case["test.csv"], register=True)["position_rms_mm"]
        assert t.values[0] == pytest.approx(expected, rel=1e-9)
        assert t.user_attrs["cv_rms_mm"] > 0 and t.user_attrs["holdout_rms_mm"] == t.values[0]
    # the refitted best scores the held-out series as its trial did
    best = min(trials, key=lambda t: t.values[0])
    assert outcome.best_run["holdout"]["position_rms_mm"] == pytest.approx(best.values[0], rel=1e-9)
    with pytest.raises(TorchcalError, match="holdout needs"):
        StudyConfig(holdout="b.csv", search_space=study.search_space).validate()


def test_distribution_contains():
    d = Distribution.parse("k", {"type": "int", "low": 20, "high": 240, "step": 20})
    assert d.contains(80) and not d.contains(90) and not d.contains(260) and not d.contains(True)
    c = Distribution.parse("k", {"type": "categorical", "choices": ["elm", "mlp"]})
    assert c.contains("mlp") and not c.contains("mma-elm")


@pytest.mark.slow
def test_study_on_measurement_files_refits_and_exports_the_best(tmp_path):
    """A study over a user's own files: objective on their validation split, best refitted, exported."""
    import json

    import optuna

    from torchcal.instruments.tracker.twin_case import write_twin_case
    from torchcal.sim.twin import TwinConfig

    case = write_twin_case(tmp_path / "case", TwinConfig(seed=2, n_train=200, n_test=80, gravity=True, gear=True))
    base = _small_base(tmp_path)
    base.export = True
    base.export_dir = str(tmp_path / "exported")
    study = StudyConfig(name="files", n_trials=3, sampler="random", pruner="none",
                        robot=str(case["robot.yaml"]), train=str(case["train.csv"]), test=str(case["test.csv"]),
                        search_space={"fit.residual_hidden": {"type": "categorical", "choices": [10, 30]}})
    outcome = run_study(base, study)
    trials = optuna.load_study(study_name="files", storage=outcome.storage).trials
    assert all(t.state.name == "COMPLETE" for t in trials) and len(trials) == 3
    assert all(t.user_attrs["test_rms_mm"] > 0 for t in trials)
    # the twin was not simulated: the data came from the files
    assert not (outcome.study_dir / "cases").exists()
    model = outcome.study_dir / "best" / "model"
    assert (model / "calibration.json").is_file() and (model / "config.yaml").is_file()
    manifest = json.loads((tmp_path / "exported" / "studies" / "files" / "best" / "manifest.json").read_text())
    assert manifest["robot"]
    assert outcome.best_run["test"]["model"]["n_poses"] == 80
    with pytest.raises(TorchcalError, match="go together"):
        StudyConfig(train="x.csv", search_space=study.search_space).validate()


def test_the_geometric_part_of_a_trial_runs_on_one_thread(tmp_path, monkeypatch):
    """A worker given two threads still fits the geometry on one, as ``fit`` does (core.threads):
    side by side, workers whose small solves were split across threads spin-waited for each other's
    cores (two workers on two cores took 2-6x longer)."""
    import torch

    from torchcal.studies import objective as module

    seen: list[int] = []

    class Stop(Exception):
        pass

    def record(*_args, **_kwargs):
        seen.append(torch.get_num_threads())
        raise Stop

    monkeypatch.setattr(module, "fit_with_selection", record)
    study = StudyConfig(name="threads", n_trials=1, search_space={"fit.residual_hidden": {"type": "int", "low": 20,
                                                                                          "high": 40}})
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with pytest.raises(Stop):
            module.StudyObjective(_small_base(tmp_path), study, tmp_path).prepare(_small_base(tmp_path))
        assert torch.get_num_threads() == 2  # given back after the fit
    finally:
        torch.set_num_threads(previous)
    assert seen == [1]
