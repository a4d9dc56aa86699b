"""``key=value`` overrides merged into a configuration dataclass (the command line's options).

Every command and instrument parses its options through :func:`apply_overrides` (reached through
:func:`torchcal.config.compose.compose_options`, the one override path), so an unknown
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
    check_values(config, overrides)
    base = OmegaConf.structured(config)
    try:
        merged = OmegaConf.merge(base, OmegaConf.from_dotlist(overrides))
    except OmegaConfBaseException as exc:
        msg = str(exc).splitlines()[0]
        key = getattr(exc, "full_key", None)
        raise TorchcalError(f"invalid override{f' (key {key!r})' if key else ''}: {msg}") from None
    return cast(T, OmegaConf.to_object(merged))  # the structured config's own dataclass


#: The longest option value (Python refuses integers of more than 4300 digits deep inside OmegaConf).
MAX_VALUE_CHARS = 4096

#: What a boolean option accepts (OmegaConf would also take any integer, 2 as true).
_BOOLEAN_WORDS = ("true", "false", "yes", "no", "on", "off", "1", "0")


def _is_bool_field(config: Any, dotted: str) -> bool:
    """Whether ``dotted`` names a ``bool`` field of the configuration dataclass ``config``."""
    target = config
    *parents, name = dotted.split(".")
    for part in parents:
        target = getattr(target, part, None)
        if target is None or not is_dataclass(target):
            return False
    if not is_dataclass(target):
        return False
    kinds = {f.name: f.type for f in fields(target)}
    return kinds.get(name) in (bool, "bool")


def check_seed(value: Any, what: str = "seed") -> None:
    """Refuse a seed that numpy and scikit-learn cannot take (an integer in [0, 2**32 - 1])."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 2**32 - 1:
        raise TorchcalError(f"{what} must be an integer in [0, 4294967295], got {value!r}")


def check_device(value: str, what: str = "device") -> None:
    """Refuse a torch device this machine cannot compute on (``meta``, an absent GPU, a typo)."""
    import torch  # here, not at the top: option parsing also serves --help, which should not load torch

    try:
        device = torch.device(value)
    except (RuntimeError, TypeError) as exc:
        raise TorchcalError(f"{what} {value!r} is not a torch device ({str(exc).splitlines()[0]}); use cpu or cuda") from None
    if device.type == "cpu":
        return
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise TorchcalError(f"{what} {value!r}: this torch build or machine has no CUDA GPU; use device=cpu")
        if device.index is not None and device.index >= count:
            raise TorchcalError(f"{what} {value!r}: this machine has {count} CUDA GPU(s) (cuda:0..cuda:{count - 1})")
        return
    raise TorchcalError(f"{what} {value!r}: torchcal computes on cpu or cuda, not {device.type}")


def check_values(config: Any, overrides: list[str]) -> None:
    """Refuse ``key=value`` items whose value would fail deep inside OmegaConf, numpy or torch.

    Every override path calls this (:func:`apply_overrides` and the composed configurations):
    ``${...}`` interpolations, a boolean field given anything but true/false (OmegaConf takes 2 as
    true), a ``seed`` outside 32 bits, a ``device`` this machine cannot compute on.
    ``config``: the configuration dataclass (instance) the items set, for field types.
    """
    for item in overrides:
        key, _, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if len(value) > MAX_VALUE_CHARS:
            raise TorchcalError(f"option {key}: a value of {len(value)} characters (at most {MAX_VALUE_CHARS}); "
                                "options are short values, file paths or short lists")
        if "${" in value:
            raise TorchcalError(f"option {key}: '{value}' holds an interpolation ('${{...}}'); options take plain values")
        if _is_bool_field(config, key) and value.lower() not in _BOOLEAN_WORDS:
            raise TorchcalError(f"option {key} is true or false, got {value!r}")
        last = key.rsplit(".", 1)[-1]
        if last == "seed":
            try:
                seed = int(value)
            except ValueError:
                raise TorchcalError(f"option {key} must be an integer in [0, 4294967295], got {value!r}") from None
            check_seed(seed, f"option {key}")
        elif last == "device":
            check_device(value, f"option {key}")


def field_names(config_class: Any) -> set[str]:
    """Names of the fields of a configuration dataclass (class or instance)."""
    if not is_dataclass(config_class):
        raise TypeError(f"{config_class!r} is not a dataclass")
    return {f.name for f in fields(config_class)}


def renamed_keys(overrides: list[str], renamed: dict[str, str], *, what: str) -> list[str]:
    """``overrides`` with keys of an earlier release spelled the current way (``old=v`` ->
    ``new=v``), each with a warning that the old spelling goes in the next release."""
    out = []
    for item in overrides:
        key, sep, value = item.partition("=")
        if sep and key.strip() in renamed:
            new = renamed[key.strip()]
            warnings.warn(f"{key.strip()}= on {what} is now {new}= ({key.strip()}= names a config group of the tracker fit); "
                          f"read as {new}={value}; the old spelling goes in the next release", FutureWarning, stacklevel=3)
            item = f"{new}={value}"
        out.append(item)
    return out


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
    # an open end reads "inf" with a round bracket: a finite number never reaches it
    span = (f"{left if low is not None else '('}{'-inf' if low is None else f'{low:g}'}, "
            f"{'inf' if high is None else f'{high:g}'}{right if high is not None else ')'}")
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if low_open else value >= low
    if ok and high is not None:
        ok = value < high if high_open else value <= high
    if not ok:
        raise TorchcalError(f"{name} must be a finite number in {span}, got {value!r}")
