"""In-process study pieces: search-space parsing, the objective's numbers, multi-objective report."""

from __future__ import annotations

import pytest
import torch

from torchcal.config import compose_run_config
from torchcal.core.errors import TorchcalError
from torchcal.residual.base import rms
from torchcal.studies.runner import run_study
from torchcal.studies.spec import Distribution, StudyConfig


def _small_base(tmp_path, **fit):
    base, _ = compose_run_config(["measurement=twin_small", "experiment=quick", "twin.n_train=200", "twin.n_test=100",
                                  "fit.residual=elm", f"out={tmp_path / 'runs'}", "fit.progress=false",
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


def test_objective_is_the_heads_validation_rms_and_size_grows_with_hidden(tmp_path):
    from torchcal.residual.elm import ELM
    from torchcal.studies.objective import StudyObjective

    base = _small_base(tmp_path)
    study = StudyConfig(name="size", n_trials=3, objectives=["validation_rms_mm", "model_size"], pruner="none",
                        sampler="random", refit_best=False,
                        search_space={"fit.residual_hidden": {"type": "categorical", "choices": [10, 40, 160]}})
    outcome = run_study(base, study)
    import optuna

    trials = optuna.load_study(study_name="size", storage=outcome.storage).trials
    assert len(trials) == 3 and all(t.state.name == "COMPLETE" for t in trials)
    # independent recomputation of one trial's objective from the same split and seed
    objective = StudyObjective(base, study, outcome.study_dir)
    t = trials[0]
    hidden = t.params["fit.residual_hidden"]
    data = objective.prepare(base)
    head = ELM(hidden=hidden, seed=base.fit.seed).fit(data.x[data.train], data.y[data.train])
    assert t.values[0] == pytest.approx(rms(head.predict(data.x[data.val]) - data.y[data.val]), rel=1e-9)
    # model size is the head's parameter count, so it grows with the hidden layer
    by_hidden = sorted((tr.params["fit.residual_hidden"], tr.values[1]) for tr in trials)
    sizes = [size for _, size in by_hidden]
    assert len(set(h for h, _ in by_hidden)) == 1 or sizes == sorted(sizes)
    assert sizes[0] >= 10 * 3
    report = (outcome.study_dir / "report.md").read_text()
    assert "Pareto front" in report and (outcome.study_dir / "figures" / "tradeoff.png").is_file()
    torch.testing.assert_close(torch.tensor(float(t.user_attrs["geometric_validation_rms_mm"])), torch.tensor(rms(data.y[data.val])))


def test_distribution_contains():
    d = Distribution.parse("k", {"type": "int", "low": 20, "high": 240, "step": 20})
    assert d.contains(80) and not d.contains(90) and not d.contains(260) and not d.contains(True)
    c = Distribution.parse("k", {"type": "categorical", "choices": ["elm", "mlp"]})
    assert c.contains("mlp") and not c.contains("mma-elm")


def test_study_on_measurement_files_refits_and_exports_the_best(tmp_path):
    """A study over a user's own files: objective on their validation split, best refitted, exported."""
    import json

    import optuna

    from torchcal.sim.twin import TwinConfig, write_twin_case

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
