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
