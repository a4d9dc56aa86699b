"""Experiment configuration: Hydra-style groups in ``configs/`` composed onto typed dataclasses."""

from torchcal.config.compose import (
    compose_run_config,
    config_dir,
    save_resolved_config,
    split_overrides,
)
from torchcal.config.instantiate import instantiate

__all__ = ["compose_run_config", "config_dir", "instantiate", "save_resolved_config", "split_overrides"]
