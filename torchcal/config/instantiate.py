"""Instantiate ``_target_`` nodes of a config, restricted to torchcal's own classes.

A config file is data a user may have received from someone else; letting it name any importable
callable (``os.system``, ``subprocess.Popen``) would make loading a config equivalent to running
code. Only targets inside the ``torchcal`` package are accepted, checked recursively before
anything is imported.
"""

from __future__ import annotations

from typing import Any

from torchcal.core.errors import TorchcalError

ALLOWED_PREFIX = "torchcal."


def _check_targets(node: Any, where: str = "config") -> None:
    if isinstance(node, dict):
        target = node.get("_target_")
        if target is not None and not (isinstance(target, str) and target.startswith(ALLOWED_PREFIX)):
            raise TorchcalError(f"{where}: _target_ '{target}' is not a torchcal class; configs may only instantiate torchcal's own classes")
        for key, value in node.items():
            _check_targets(value, f"{where}.{key}")
    elif isinstance(node, list):
        for k, value in enumerate(node):
            _check_targets(value, f"{where}[{k}]")


def instantiate(node: Any, **kwargs: Any) -> Any:
    """``hydra.utils.instantiate`` after checking every ``_target_`` is under ``torchcal.``."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    plain = OmegaConf.to_container(node, resolve=True) if isinstance(node, (DictConfig, ListConfig)) else node
    _check_targets(plain)
    from hydra.utils import instantiate as hydra_instantiate

    return hydra_instantiate(plain, **kwargs)
