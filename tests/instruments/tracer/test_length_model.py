"""The tracer's length model: simulated lengths, whitened residuals at the truth, a start that fits, gradients."""

from __future__ import annotations

import torch

from torchcal.instruments.tracer.length_model import TracerLengthModel
from torchcal.instruments.tracer.lengths import station_distances
from torchcal.instruments.tracer.plan import plan_tracer_setup

N_POINTS = 40


def _tracer():
    g = torch.Generator().manual_seed(8)
    plan = plan_tracer_setup(torch.tensor([0.7, 0.0, 0.5]), 0.3, N_POINTS, 4, g)
    dead = station_distances(plan.points[:1], plan.stations)[0]
    return TracerLengthModel(plan.stations, dead), plan.points


def _true_params(model: TracerLengthModel) -> torch.Tensor:
    return torch.cat([model.stations_m.reshape(-1), model.dead_paths_m])


def _case():
    return _tracer()


def test_simulated_columns_are_lengths():
    instrument, points = _case()
    cols = instrument.simulate(points, torch.Generator().manual_seed(0))
    assert list(cols) == [f"l{k}" for k in range(1, instrument.n_stations + 1)]
    assert all(v.shape == (N_POINTS,) and v.dtype == torch.float64 for v in cols.values())


def test_residuals_are_whitened_at_the_truth():
    instrument, points = _case()
    cols = instrument.simulate(points, torch.Generator().manual_seed(1))
    r = instrument.residuals(points, cols, _true_params(instrument))
    assert 0.75 < r.pow(2).mean().sqrt().item() < 1.25


def test_initial_params_fit_the_measurements():
    instrument, points = _case()
    cols = instrument.simulate(points, torch.Generator().manual_seed(3))
    params = instrument.initial_params(points, cols)
    assert instrument.residuals(points, cols, params).pow(2).mean().sqrt().item() < 1.2


def test_residuals_are_differentiable():
    instrument, points = _case()
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
