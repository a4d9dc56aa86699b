"""Shared stiffness fixtures: one loading-rig twin, its training and test experiments."""

from __future__ import annotations

import pytest
import torch

from torchcal.instruments.stiffness.twin import StiffnessTwin, StiffnessTwinConfig
from torchcal.kinematics.robot import default_robot_path, load_robot


@pytest.fixture(scope="session")
def robot():
    return load_robot(default_robot_path())


@pytest.fixture(scope="session")
def rig():
    """Twin, 120 training and 200 test poses (positions, rotations, unloaded points)."""
    twin = StiffnessTwin(StiffnessTwinConfig(seed=7))
    gen = torch.Generator().manual_seed(11)
    return twin, twin.sample(120, gen), twin.sample(200, gen)
