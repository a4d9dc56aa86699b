"""A calibrated twin (geometric errors only) and its export, built once per test session."""

from __future__ import annotations

import pytest
import torch

from torchcal.config.schema import FitConfig
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit, save_fit


@pytest.fixture(scope="session")
def twin() -> Twin:
    return Twin.create(TwinConfig(seed=3, gravity=False, gear=False))


@pytest.fixture(scope="session")
def model_dir(twin, tmp_path_factory):
    gen = torch.Generator().manual_seed(11)
    train = twin.sample(150, gen)
    result = fit(twin.robot, train, FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none"))
    return save_fit(tmp_path_factory.mktemp("model") / "model", twin.robot, train, result, {})


@pytest.fixture(scope="session")
def exported(model_dir, tmp_path_factory):
    from torchcal.compensate.export import export_model

    out = tmp_path_factory.mktemp("export")
    return out, export_model(model_dir, out)
