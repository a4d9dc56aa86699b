"""``key=value`` overrides merged into a configuration dataclass (the command line's options).

Every command and instrument parses its options through :func:`apply_overrides`, so an unknown
key, a wrong type or a malformed item gets the same one-line error everywhere. Options that belong
to another command's configuration (a tracker-fit key given to a stiffness fit) are taken out by
:func:`split_foreign_keys` and reported with one warning instead of failing.
"""

from __future__ import annotations

import warnings
from dataclasses import fields, is_dataclass
from typing import Any, TypeVar, cast

from torchcal.core.errors import TorchcalError

T = TypeVar("T")


def apply_overrides(config: T, overrides: list[str]) -> T:
    """``config`` with ``key=value`` strings merged in (dotted keys for nested fields).

    Raises:
        TorchcalError: an item without ``=``, an unknown key or a value of the wrong type.
    """
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    bad = [o for o in overrides if "=" not in o]
    if bad:
        raise TorchcalError(f"override '{bad[0]}' is not of the form key=value")
    base = OmegaConf.structured(config)
    try:
        merged = OmegaConf.merge(base, OmegaConf.from_dotlist(overrides))
    except OmegaConfBaseException as exc:
        msg = str(exc).splitlines()[0]
        raise TorchcalError(f"invalid override: {msg}") from None
    return cast(T, OmegaConf.to_object(merged))  # the structured config's own dataclass


def field_names(config_class: Any) -> set[str]:
    """Names of the fields of a configuration dataclass (class or instance)."""
    if not is_dataclass(config_class):
        raise TypeError(f"{config_class!r} is not a dataclass")
    return {f.name for f in fields(config_class)}


def split_foreign_keys(overrides: list[str], own: Any, foreign: Any, *, what: str) -> list[str]:
    """The overrides that ``own`` accepts; those only ``foreign`` knows are dropped with one warning.

    Args:
        overrides: ``key=value`` items (the top-level key decides).
        own: configuration dataclass of the command that runs.
        foreign: configuration dataclass whose keys users may pass out of habit (the tracker fit's).
        what: the file kind, for the warning (``"a stiffness file"``).
    """
    foreign_only = field_names(foreign) - field_names(own)
    kept: list[str] = []
    ignored: list[str] = []
    for item in overrides:
        key = item.partition("=")[0].strip().split(".")[0]
        (ignored if key in foreign_only else kept).append(item)
    if ignored:
        warnings.warn(f"ignored for {what}: {', '.join(ignored)}", stacklevel=3)
    return kept


def check_range(config: Any, name: str, *, low: float | None = None, high: float | None = None,
                low_open: bool = False, high_open: bool = False) -> None:
    """Refuse a numeric option of ``config`` that is not finite or lies outside ``[low, high]``.

    ``low_open`` / ``high_open`` exclude the bound itself. The message names the option, its value
    and the range, e.g. ``parallel_threshold_deg must be a finite number in [0, 90), got -5.0``.
    """
    import math

    value = getattr(config, name)
    left, right = "(" if low_open else "[", ")" if high_open else "]"
    span = f"{left}{'-inf' if low is None else f'{low:g}'}, {'inf' if high is None else f'{high:g}'}{right}"
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value < high if high_open else value <= high
    if not ok:
        raise TorchcalError(f"{name} must be a finite number in {span}, got {value!r}")
