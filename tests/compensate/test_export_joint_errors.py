"""Export refuses model folders with joint-space errors: the graph evaluates the chain at the commanded joints."""

from __future__ import annotations

import pytest
import torch

from torchcal.compensate.export import export_model
from torchcal.errors import TorchcalError
from torchcal.pipeline import FitConfig, fit, save_fit


@pytest.mark.parametrize("option", [{"joint_harmonics": "first"}, {"gravity_compliance": "wrist"}])
def test_export_refuses_models_with_joint_space_errors(twin, tmp_path, option):
    train = twin.sample(120, torch.Generator().manual_seed(5))
    result = fit(twin.robot, train, FitConfig(residual="none", progress=False, **option))
    folder = save_fit(tmp_path / "model", twin.robot, train, result, {})
    key = next(iter(option))
    with pytest.raises(TorchcalError, match=f"no joint-space error term \\({key}\\).*{key}=none"):
        export_model(folder, tmp_path / "export")
    assert not (tmp_path / "export").exists()  # refused before anything is written
