"""Fixtures shared by the lifecycle tests (``check``, ``update``)."""

from __future__ import annotations

import pytest
import torch

from torchcal.config.schema import FitConfig
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.pipeline import fit_model
from torchcal.stages.store import load_model


@pytest.fixture(scope="session")
def calibrated(tmp_path_factory):
    """``(twin, stored)``: a twin calibrated on 150 poses (geometry, no head), the model before any change.

    Session-scoped and shared: tests read it and write only into folders of their own."""
    twin = Twin.create(TwinConfig(seed=3))
    train = twin.sample(150, torch.Generator().manual_seed(11))
    folder = tmp_path_factory.mktemp("calibrated") / "model"
    fit_model(folder, twin.robot, train, FitConfig(residual="none", progress=False))
    return twin, load_model(folder)
