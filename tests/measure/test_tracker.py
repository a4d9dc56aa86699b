"""The laser-tracker instrument: simulated points in an unknown rigid frame."""

from __future__ import annotations

import pytest
import torch

from torchcal.errors import DataError
from torchcal.kinematics.transforms import homogeneous, so3_exp
from torchcal.measure import TrackerInstrument


def _frame() -> torch.Tensor:
    return homogeneous(so3_exp(torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64)), torch.tensor([1.5, -0.4, 0.2], dtype=torch.float64))


def test_simulated_points_are_the_true_points_in_the_tracker_frame():
    g = torch.Generator().manual_seed(0)
    points = torch.rand(5000, 3, generator=g, dtype=torch.float64)
    tracker = TrackerInstrument(sigma_m=30e-6, T_instrument_base=_frame())
    cols = tracker.simulate(points, g)
    assert list(cols) == ["x", "y", "z"]
    exact = points @ _frame()[:3, :3].T + _frame()[:3, 3]
    noise = torch.stack([cols["x"], cols["y"], cols["z"]], -1) - exact
    assert abs(noise.std().item() / 30e-6 - 1.0) < 0.03 and noise.mean().abs().item() < 2e-6


def test_initial_params_recover_the_frame():
    g = torch.Generator().manual_seed(1)
    points = torch.rand(50, 3, generator=g, dtype=torch.float64)
    tracker = TrackerInstrument(sigma_m=10e-6, T_instrument_base=_frame())
    cols = tracker.simulate(points, g)
    params = tracker.initial_params(points, cols)
    torch.testing.assert_close(so3_exp(params[:3]), _frame()[:3, :3], atol=1e-4, rtol=0)
    torch.testing.assert_close(params[3:], _frame()[:3, 3], atol=1e-4, rtol=0)
    r = tracker.residuals(points, cols, params)
    assert r.shape == (150,) and 0.7 < r.pow(2).mean().sqrt().item() < 1.1  # 6 of 150 dof absorbed


def test_missing_rows_and_columns():
    tracker = TrackerInstrument()
    points = torch.zeros(4, 3, dtype=torch.float64)
    cols = tracker.simulate(points)
    cols["y"][1] = torch.nan
    assert tracker.residuals(points, cols, torch.zeros(6, dtype=torch.float64)).shape == (9,)
    del cols["z"]
    with pytest.raises(DataError, match="missing z"):
        tracker.residuals(points, cols, torch.zeros(6, dtype=torch.float64))
    assert tracker.columns(6) == ["q1", "q2", "q3", "q4", "q5", "q6", "x", "y", "z"]
