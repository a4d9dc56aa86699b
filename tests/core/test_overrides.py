"""key=value overrides: merged into the dataclass, bad items refused in one line, foreign keys dropped with a warning."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from torchcal.core.errors import TorchcalError
from torchcal.core.overrides import apply_overrides, split_foreign_keys


@dataclass
class _Inner:
    n: int = 3


@dataclass
class _Own:
    rate: float = 0.5
    name: str = "a"
    inner: _Inner = field(default_factory=_Inner)


@dataclass
class _Other:
    rate: float = 0.1
    method: str = "lm"


def test_overrides_set_typed_and_nested_fields():
    config = apply_overrides(_Own(), ["rate=0.25", "inner.n=7", "name=b"])
    assert (config.rate, config.inner.n, config.name) == (0.25, 7, "b")


@pytest.mark.parametrize("item, message", [("rate", "is not of the form key=value"), ("speed=1", "invalid override"),
                                           ("rate=fast", "invalid override")])
def test_bad_overrides_are_one_clear_error(item, message):
    with pytest.raises(TorchcalError, match=message):
        apply_overrides(_Own(), [item])


def test_keys_of_another_command_are_dropped_with_one_warning():
    with pytest.warns(UserWarning, match=r"ignored for a test file: method=gn, method\.x=1"):
        kept = split_foreign_keys(["rate=1", "method=gn", "method.x=1", "speed=2"], _Own, _Other, what="a test file")
    assert kept == ["rate=1", "speed=2"]  # shared keys and unknown keys stay (unknown ones fail in apply_overrides)


@dataclass
class _Run:
    flag: bool = True
    seed: int = 0
    device: str = "cpu"
    name: str = "a"
    inner: _Inner = field(default_factory=_Inner)


@pytest.mark.parametrize("item, message", [
    ("flag=2", "flag is true or false"), ("flag=maybe", "flag is true or false"),
    ("seed=4294967296", r"seed must be an integer in \[0, 4294967295\]"), ("seed=-1", "seed must be an integer"),
    ("seed=1.5", "seed must be an integer"), ("device=meta", "cpu or cuda, not meta"),
    ("device=banana", "not a torch device"), ("name=${oc.env:HOME}", "interpolation"),
])
def test_options_that_would_fail_deep_are_refused_where_they_are_parsed(item, message):
    with pytest.raises(TorchcalError, match=message):
        apply_overrides(_Run(), [item])


def test_cuda_is_refused_where_there_is_none():
    import torch

    if torch.cuda.is_available():
        assert apply_overrides(_Run(), ["device=cuda"]).device == "cuda"
    else:
        with pytest.raises(TorchcalError, match="no CUDA GPU"):
            apply_overrides(_Run(), ["device=cuda"])


def test_plain_boolean_words_and_edge_seeds_pass():
    config = apply_overrides(_Run(), ["flag=false", "seed=4294967295", "device=cpu"])
    assert (config.flag, config.seed, config.device) == (False, 4294967295, "cpu")
    assert apply_overrides(_Run(), ["flag=yes"]).flag is True


@pytest.mark.parametrize("module, factory", [("torchcal.instruments.stiffness.commands", "stiffness_config"),
                                             ("torchcal.instruments.profile.commands", "profile_config")])
def test_model_folder_option_is_model_dir_and_the_old_spelling_still_works(module, factory, tmp_path):
    """``model=`` names a config group for tracker fits; the model folder of stiffness and profile files is
    ``model_dir=``. The old spelling is read for one release, with a warning."""
    import importlib
    import warnings

    make = getattr(importlib.import_module(module), factory)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the new spelling warns about nothing
        assert make([f"model_dir={tmp_path}"]).model_dir == str(tmp_path)
    with pytest.warns(FutureWarning, match=r"model= on a \w+ file is now model_dir="):
        assert make([f"model={tmp_path}"]).model_dir == str(tmp_path)
