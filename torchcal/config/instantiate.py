"""Instantiate ``_target_`` nodes of a config, restricted to torchcal's own classes.

A config file is data a user may have received from someone else; letting it name any importable
callable (``os.system``, ``subprocess.Popen``) would make loading a config equivalent to running
code. Only classes defined inside the ``torchcal`` package are accepted, named by the dotted path
where they are defined: a target is resolved (importing ``torchcal`` modules only) and refused
unless it is a class whose ``__module__`` is under ``torchcal.`` and whose own module and name are
the target, so that a path through another module's attribute (``torchcal.core.io.os.makedirs``,
``torchcal.core.io.Path``) or a torchcal function (``torchcal.core.io.atomic_write_text``) is
refused. Every target is checked, recursively, before anything is instantiated.
"""

from __future__ import annotations

import importlib
from typing import Any

from torchcal.core.errors import TorchcalError

ALLOWED_PREFIX = "torchcal."
_REFUSED = "configs may only instantiate torchcal's own classes, named where they are defined"


def _resolve(target: str) -> Any:
    """The object ``target`` names: the longest importable ``torchcal`` module prefix, then attributes.
    ``None`` where nothing of that name exists."""
    parts = target.split(".")
    for cut in range(len(parts) - 1, 0, -1):
        module_name = ".".join(parts[:cut])
        try:
            obj: Any = importlib.import_module(module_name)
        except ImportError:
            continue
        for name in parts[cut:]:
            if name.startswith("_") or not hasattr(obj, name):
                return None
            obj = getattr(obj, name)
        return obj
    return None


def _check_target(target: Any, where: str) -> None:
    if not (isinstance(target, str) and target.startswith(ALLOWED_PREFIX)):
        raise TorchcalError(f"{where}: _target_ '{target}' is not a torchcal class; {_REFUSED}")
    obj = _resolve(target)
    if obj is None:
        raise TorchcalError(f"{where}: _target_ '{target}' names nothing in torchcal; {_REFUSED}")
    if not isinstance(obj, type):
        raise TorchcalError(f"{where}: _target_ '{target}' is a {type(obj).__name__}, not a torchcal class; {_REFUSED}")
    defined = f"{obj.__module__}.{obj.__qualname__}"
    if not defined.startswith(ALLOWED_PREFIX):
        raise TorchcalError(f"{where}: _target_ '{target}' is {defined}, not a torchcal class; {_REFUSED}")
    if defined != target:
        raise TorchcalError(f"{where}: _target_ '{target}' is the class {defined}; name it where it is defined")


def _check_targets(node: Any, where: str = "config") -> None:
    if isinstance(node, dict):
        if "_target_" in node:
            _check_target(node["_target_"], where)
        for key, value in node.items():
            _check_targets(value, f"{where}.{key}")
    elif isinstance(node, list):
        for k, value in enumerate(node):
            _check_targets(value, f"{where}[{k}]")


def instantiate(node: Any, **kwargs: Any) -> Any:
    """``hydra.utils.instantiate`` after checking every ``_target_`` is a class defined under ``torchcal.``
    (``kwargs`` are checked too: a ``_target_`` there would be instantiated as well)."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    plain = OmegaConf.to_container(node, resolve=True) if isinstance(node, (DictConfig, ListConfig)) else node
    _check_targets(plain)
    extra = {k: OmegaConf.to_container(v, resolve=True) if isinstance(v, (DictConfig, ListConfig)) else v
             for k, v in kwargs.items()}
    _check_targets(extra, "config")
    from hydra.utils import instantiate as hydra_instantiate

    return hydra_instantiate(plain, **extra)
