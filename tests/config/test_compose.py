"""configs/ composition: groups, dotted overrides onto the schema, clear errors, safe instantiate."""

import pytest
from omegaconf import OmegaConf

from torchcal.config import compose_run_config, instantiate, save_resolved_config
from torchcal.config.compose import merge_section
from torchcal.config.schema import FitConfig, RunConfig
from torchcal.core.errors import TorchcalError
from torchcal.studies.spec import StudyConfig


def test_default_composition_is_the_main_job():
    config, _ = compose_run_config([])
    assert isinstance(config, RunConfig)
    # The configs reproduce the documented default run: 1500/600 twin with non-geometric errors.
    assert (config.twin.n_train, config.twin.n_test, config.twin.gravity, config.twin.gear) == (1500, 600, True, True)
    assert config.fit == FitConfig()
    assert config.name == "twin-default" and config.export


def test_group_selection_and_dotted_override_combine():
    config, _ = compose_run_config(["model=mlp", "measurement=twin_small", "twin.n_train=33", "fit.seed=4", "name=x"])
    assert config.fit.residual == "mlp"
    assert config.twin.n_train == 33 and config.twin.n_test == 200
    assert config.fit.seed == 4 and config.name == "x"


@pytest.mark.parametrize(
    "override, message",
    [
        ("fit.residual_hiden=3", "residual_hiden"),
        ("twin.n_train=many", "n_train"),
        ("model=no_such_model", "no_such_model"),
        ("fit.seed", "not of the form key=value"),
    ],
)
def test_bad_overrides_name_the_key(override, message):
    with pytest.raises(TorchcalError, match=message):
        compose_run_config([override])


def test_study_section_is_split_and_typed():
    base, sections = compose_run_config(["study=elm_mayfly", "study.n_trials=7"], config_name="study", extra_sections=("study",))
    study = merge_section(StudyConfig(), sections["study"])
    assert study.n_trials == 7 and study.name == "elm_mayfly"
    assert set(study.search_space) == {"fit.residual_hidden", "fit.mayfly_population"}
    study.validate()
    assert base.fit.residual == "mma-elm"


def test_resolved_config_round_trips(tmp_path):
    config, _ = compose_run_config(["model=elm", "twin.seed=9"])
    path = save_resolved_config(tmp_path / "config.yaml", config)
    loaded = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(RunConfig()), OmegaConf.load(path)))
    assert loaded == config


def test_instantiate_only_torchcal_classes():
    obj = instantiate({"_target_": "torchcal.optimize.mayfly.Mayfly", "population": 7, "iterations": 3})
    assert type(obj).__name__ == "Mayfly" and obj.population == 7
    for target in ("os.system", "subprocess.Popen", "torchcalx.evil"):
        with pytest.raises(TorchcalError, match="not a torchcal class"):
            instantiate({"inner": [{"_target_": target, "command": "true"}]})


def test_fit_config_takes_the_model_group():
    from torchcal.config.compose import compose_fit_config

    config = compose_fit_config(["model=lasso", "seed=5"])
    assert (config.method, config.residual, config.seed) == ("lasso", "none", 5)
    assert compose_fit_config([]) == FitConfig()
    with pytest.raises(TorchcalError, match="only the model group"):
        compose_fit_config(["study=elm_mayfly"])


def test_one_override_path_for_every_command():
    """Every command's options go through compose_options: the same checks and messages whatever the
    dataclass, a field named like a config group is a field, and a group the command does not take
    is refused in one line."""
    from torchcal.config.compose import compose_fit_config, compose_options
    from torchcal.config.schema import FitConfig
    from torchcal.instruments.registry import get

    stiffness = get("stiffness").options()
    for schema in (FitConfig(), stiffness()):
        with pytest.raises(TorchcalError, match="invalid override"):
            compose_options(schema, ["cv_folds=three"])
        with pytest.raises(TorchcalError, match=r"cv_folds must be a finite number in \[2, 100\]"):
            compose_options(schema, ["cv_folds=1"])
        with pytest.raises(TorchcalError, match="split must be one of grouped, blocks, random, got 'loo'"):
            compose_options(schema, ["split=loo"])
    assert compose_options(FitConfig(), ["cv_folds=3"]).cv_folds == 3
    twin = get("sockets").twin().config_factory()
    assert compose_options(twin, ["robot=my.yaml"]).robot == "my.yaml"
    with pytest.raises(TorchcalError, match="no config group applies to this command"):
        compose_options(stiffness(), ["experiment=quick"])
    with pytest.raises(TorchcalError, match="only the model group applies to this command"):
        compose_fit_config(["experiment=quick"])
