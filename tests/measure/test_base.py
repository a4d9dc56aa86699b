"""Contract every instrument must meet, run on each registered implementation."""

from __future__ import annotations

import pytest
import torch

from torchcal.kinematics.transforms import homogeneous, so3_exp
from torchcal.measure import INSTRUMENTS, Instrument, TrackerInstrument, TracerInstrument, plan_tracer_setup
from torchcal.measure.lengths import station_distances

N_POINTS = 40


def _tracker():
    frame = homogeneous(so3_exp(torch.tensor([0.1, 0.2, -0.3], dtype=torch.float64)), torch.tensor([2.0, 0.5, -0.1], dtype=torch.float64))
    return TrackerInstrument(sigma_m=20e-6, T_instrument_base=frame), None


def _tracer():
    g = torch.Generator().manual_seed(8)
    plan = plan_tracer_setup(torch.tensor([0.7, 0.0, 0.5]), 0.3, N_POINTS, 4, g)
    dead = station_distances(plan.points[:1], plan.stations)[0]
    return TracerInstrument(plan.stations, dead), plan.points


def _true_params(instrument: Instrument) -> torch.Tensor:
    if isinstance(instrument, TrackerInstrument):
        from torchcal.kinematics.transforms import so3_log

        t = instrument.T_instrument_base
        return torch.cat([so3_log(t[:3, :3]), t[:3, 3]])
    return torch.cat([instrument.stations_m.reshape(-1), instrument.dead_paths_m])


@pytest.fixture(params=["tracker", "tracer"])
def case(request):
    instrument, points = {"tracker": _tracker, "tracer": _tracer}[request.param]()
    if points is None:
        g = torch.Generator().manual_seed(2)
        points = torch.rand(N_POINTS, 3, generator=g, dtype=torch.float64)
    return instrument, points


def test_registry_lists_every_instrument():
    assert set(INSTRUMENTS) == {"tracker", "tracer"}
    assert all(issubclass(cls, Instrument) and INSTRUMENTS[name] is cls for name, cls in INSTRUMENTS.items())


def test_columns_and_simulation_agree(case):
    instrument, points = case
    cols = instrument.simulate(points, torch.Generator().manual_seed(0))
    names = instrument.columns(6)
    assert names[:6] == [f"q{k}" for k in range(1, 7)] and names[6:] == list(cols)
    assert all(v.shape == (N_POINTS,) and v.dtype == torch.float64 for v in cols.values())


def test_residuals_are_whitened_at_the_truth(case):
    instrument, points = case
    cols = instrument.simulate(points, torch.Generator().manual_seed(1))
    r = instrument.residuals(points, cols, _true_params(instrument))
    assert 0.75 < r.pow(2).mean().sqrt().item() < 1.25


def test_initial_params_fit_the_measurements(case):
    instrument, points = case
    cols = instrument.simulate(points, torch.Generator().manual_seed(3))
    params = instrument.initial_params(points, cols)
    assert instrument.residuals(points, cols, params).pow(2).mean().sqrt().item() < 1.2


def test_residuals_are_differentiable(case):
    instrument, points = case
    cols = instrument.simulate(points, torch.Generator().manual_seed(4))
    params = _true_params(instrument).clone().requires_grad_(True)
    pts = points.clone().requires_grad_(True)
    loss = instrument.residuals(pts, cols, params).pow(2).sum()
    g_pts, g_par = torch.autograd.grad(loss, (pts, params))
    h = 1e-8
    for tensor, grad, idx in [(points, g_pts, (3, 1)), (_true_params(instrument), g_par, (2,))]:
        plus, minus = tensor.clone(), tensor.clone()
        plus[idx] += h
        minus[idx] -= h
        args = (lambda t: (t, cols, _true_params(instrument))) if tensor is points else (lambda t: (points, cols, t))
        fd = (instrument.residuals(*args(plus)).pow(2).sum() - instrument.residuals(*args(minus)).pow(2).sum()) / (2 * h)
        assert abs(fd.item() - grad[idx].item()) <= 1e-4 * max(1.0, abs(grad[idx].item()))
