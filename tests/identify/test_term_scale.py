"""TermScaleProblem: its analytic Jacobian against central finite differences; scale 0 is the stored term."""

from __future__ import annotations

import torch

from torchcal.identify.term_scale import TermScaleProblem
from torchcal.kinematics.error_model import ErrorModel
from torchcal.sim.twin import Twin, TwinConfig


def _problem():
    twin = Twin.create(TwinConfig(seed=4))
    data = twin.sample(8, torch.Generator().manual_seed(1))
    model = ErrorModel(twin.robot, T_instrument_base=twin.T_instrument_base())
    gen = torch.Generator().manual_seed(2)
    terms = 1e-3 * torch.randn(2, len(data), twin.robot.dof, generator=gen, dtype=torch.float64)
    size = model.layout.size
    free = torch.tensor([model.layout.index("a2"), model.layout.index("theta3"), model.layout.index("tool_z"), size, size + 1])
    x = torch.cat([twin.x_true.clone(), torch.tensor([0.3, -0.7], dtype=torch.float64)])
    weights = torch.linspace(0.5, 2.0, len(data), dtype=torch.float64)
    return TermScaleProblem(model, data, terms, free, ["c_scale", "h_scale"], weights=weights), x, model, data, terms


def test_jacobian_matches_finite_differences():
    problem, x, *_ = _problem()
    r, jac = problem.jacobian(x)
    assert torch.allclose(r, problem.residuals(x))
    h = 1e-7
    for k, i in enumerate(problem.free.tolist()):
        step = torch.zeros_like(x)
        step[i] = h
        numeric = (problem.residuals(x + step) - problem.residuals(x - step)) / (2 * h)
        assert torch.allclose(jac[:, k], numeric, atol=1e-6 * float(numeric.abs().max())), problem.names[k]


def test_scale_zero_is_the_stored_term_and_minus_one_removes_it():
    problem, x, model, data, terms = _problem()
    x = x.clone()
    x[-2:] = 0.0
    expected = (data.position - model.tcp_position(data.q + terms.sum(0), x[: model.layout.size])) * problem.weights[:, None]
    assert torch.allclose(problem.residuals(x), expected.reshape(-1))
    x[-2:] = -1.0
    bare = (data.position - model.tcp_position(data.q, x[: model.layout.size])) * problem.weights[:, None]
    assert torch.allclose(problem.residuals(x), bare.reshape(-1))
