"""Config input a hostile user may give: instantiate targets reached through another module, malformed
YAML in a group file, misspelt keys and groups, a named config folder that is not one."""

import shutil
from pathlib import Path

import pytest

from torchcal.config import compose_run_config, instantiate
from torchcal.config.compose import compose_fit_config, config_dir
from torchcal.core.errors import TorchcalError
from torchcal.studies.spec import StudyConfig


@pytest.mark.parametrize(
    "target, message",
    [
        ("torchcal.core.io.os.makedirs", "is a function, not a torchcal class"),
        ("torchcal.core.io.tempfile.mkdtemp", "is a function, not a torchcal class"),
        ("torchcal.core.io.atomic_write_text", "is a function, not a torchcal class"),
        ("torchcal.core.io.Path", "is pathlib.Path, not a torchcal class"),
        ("torchcal.core.io.no_such_thing", "names nothing in torchcal"),
        ("torchcal.optimize.mayfly.Mayfly.__init__", "names nothing in torchcal"),
    ],
)
def test_instantiate_refuses_what_is_not_a_torchcal_class_where_defined(tmp_path, target, message):
    made = tmp_path / "made"
    with pytest.raises(TorchcalError, match=message):
        instantiate({"inner": {"_target_": target, "_args_": [str(made)]}})
    with pytest.raises(TorchcalError, match=message):
        instantiate({"_target_": "torchcal.optimize.mayfly.Mayfly"}, inner={"_target_": target, "_args_": [str(made)]})
    assert not made.exists()
    assert not list(tmp_path.iterdir())


def test_instantiate_refuses_a_torchcal_class_named_through_another_module():
    import torchcal.config.schema as schema

    assert schema.TwinConfig.__module__ == "torchcal.sim.twin_config"  # imported there, defined elsewhere
    with pytest.raises(TorchcalError, match=r"is the class torchcal\.sim\.twin_config\.TwinConfig; name it where it is defined"):
        instantiate({"_target_": "torchcal.config.schema.TwinConfig"})
    twin = instantiate({"_target_": "torchcal.sim.twin_config.TwinConfig", "n_train": 3})
    assert type(twin).__name__ == "TwinConfig" and twin.n_train == 3


@pytest.fixture
def configs(tmp_path, monkeypatch) -> Path:
    """A copy of configs/ that TORCHCAL_CONFIG_DIR points at."""
    folder = tmp_path / "configs"
    shutil.copytree(config_dir(), folder)
    monkeypatch.setenv("TORCHCAL_CONFIG_DIR", str(folder))
    return folder


@pytest.mark.parametrize(
    "text, message",
    [
        ("fit:\n  method: !!python/object/apply:os.system [\"touch {marker}\"]\n",
         r"evil\.yaml, line 2: could not determine a constructor for the tag .*python/object/apply:os\.system"),
        ("fit:\n  method: [lm\n", r"evil\.yaml, line 3: expected ',' or '\]'"),
        ("fit:\n  method: lm\n  method: gn\n",
         r"evil\.yaml, line 3: key 'method' is given twice in one mapping \(first on line 2\)"),
    ],
)
def test_malformed_group_file_is_one_line_naming_file_and_line(configs, tmp_path, text, message):
    marker = tmp_path / "ran"
    (configs / "model" / "evil.yaml").write_text(text.format(marker=marker))
    with pytest.raises(TorchcalError, match=message) as caught:
        compose_run_config(["model=evil"])
    assert "\n" not in str(caught.value) and str(configs) in str(caught.value)
    with pytest.raises(TorchcalError, match=message):
        compose_fit_config(["model=evil"])
    assert not marker.exists()


def test_malformed_study_file(configs):
    (configs / "study" / "malformed.yaml").write_text("search_space: [a\n")
    with pytest.raises(TorchcalError, match=r"malformed\.yaml, line 2: expected ',' or '\]'"):
        compose_run_config(["study=malformed"], config_name="study", extra_sections=("study",))


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["twin.n_trian=50"], r"key 'twin\.n_trian'\): no key 'n_trian' in 'twin' \(did you mean 'twin\.n_train'\?\)"),
        (["mdoel=mlp"], r"no key 'mdoel' \(did you mean 'model'\?\)"),
        (["model=mpl"], r"no option 'mpl' in config group 'model' \(did you mean 'mlp'\?\); model options: auto, elm, "
                        r"geometric, lasso, mlp, mma_elm"),
        (["model=../config"], "a config group takes the name of one of its options, not a path"),
        (["model=sub/geometric"], "not a path"),
        (["model=geometric", "model=mlp"], r"config group 'model' is given twice \('model=geometric' and 'model=mlp'\)"),
    ],
)
def test_misspelt_keys_and_groups_are_named_with_the_closest(overrides, message):
    with pytest.raises(TorchcalError, match=message):
        compose_run_config(overrides)


def test_misspelt_section_key_names_its_section():
    from torchcal.config.compose import merge_section

    _, sections = compose_run_config(["study=elm_mayfly", "study.n_trals=7"], config_name="study",
                                     extra_sections=("study",))
    with pytest.raises(TorchcalError, match=r"key 'study\.n_trals'\): no key 'n_trals' in 'study' \(did you mean "
                                            r"'study\.n_trials'\?\)"):
        merge_section(StudyConfig(), sections["study"])


def test_a_named_config_folder_that_is_none_is_refused(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHCAL_CONFIG_DIR", str(tmp_path / "nonexistent"))
    with pytest.raises(TorchcalError, match=r"TORCHCAL_CONFIG_DIR=.*nonexistent is not a folder"):
        compose_run_config([])
    monkeypatch.setenv("TORCHCAL_CONFIG_DIR", str(tmp_path))
    with pytest.raises(TorchcalError, match=r"TORCHCAL_CONFIG_DIR=.* has no config\.yaml"):
        compose_run_config(["model=mlp"])
