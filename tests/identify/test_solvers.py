"""Identifiers: closed-form check, agreement of LM / GN / LASSO, recovery of twin truth."""

from __future__ import annotations

import math

import pytest
import torch

from tests.conftest import perturbed_vector
from torchcal.data.measurements import Measurements
from torchcal.identify import IDENTIFIERS
from torchcal.identify.base import SolveResult
from torchcal.identify.calibrate import calibrate
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.problem import CalibrationProblem
from torchcal.kinematics.error_model import ErrorModel


def _twin_data(robot, generator, n=120, noise_m=2e-5):
    model = ErrorModel(robot)
    x_true = perturbed_vector(model, generator)
    x_true[model.layout.base_slice] = torch.tensor([1.2, -0.4, 0.3, 0.2, -0.3, 1.5], dtype=torch.float64)
    q = robot.sample_joints(n, generator)
    p = model.tcp_position(q, x_true) + noise_m * torch.randn(n, 3, generator=generator, dtype=torch.float64)
    return model, x_true, Measurements(q=q, position=p)


def test_lm_solves_a_closed_form_linear_case(robot, generator):
    """Fitting only the tool offset is linear in it: LM must hit the normal-equation solution."""
    model, x_true, data = _twin_data(robot, generator, n=40)
    model = ErrorModel(robot, T_instrument_base=model.instrument_from_base(x_true))
    x0 = x_true.clone()
    x0[model.layout.base_slice] = 0.0
    tool = torch.arange(model.layout.tool_slice.start, model.layout.tool_slice.start + 3)
    x0[tool] = 0.0
    problem = CalibrationProblem(model, data, tool)
    r0, jac = problem.jacobian(x0)
    closed = torch.linalg.lstsq(jac, -r0.unsqueeze(-1)).solution.squeeze(-1)
    result = LevenbergMarquardt().solve(problem, x0)
    assert torch.allclose(result.x[tool], closed, atol=1e-12)


@pytest.mark.parametrize("name", sorted(IDENTIFIERS))
def test_every_identifier_reaches_the_noise_floor(name, robot, generator):
    model, x_true, data = _twin_data(robot, generator)
    result = calibrate(robot, data, identifier=IDENTIFIERS[name]())
    assert isinstance(result.solve, SolveResult)
    q = robot.sample_joints(300, generator)
    error = (result.model.tcp_position(q, result.x) - model.tcp_position(q, x_true)).norm(dim=-1)
    # model error well below the 2e-5 m per-axis noise (averaging over 120 poses)
    assert float(error.pow(2).mean().sqrt()) < 2e-5
    assert abs(result.sigma_residual_m - 2e-5) < 0.3e-5


def test_lm_and_gauss_newton_agree(robot, generator):
    _, _, data = _twin_data(robot, generator)
    a = calibrate(robot, data, identifier=IDENTIFIERS["lm"]())
    b = calibrate(robot, data, identifier=IDENTIFIERS["gn"]())
    assert abs(a.solve.cost - b.solve.cost) <= 1e-9 * a.solve.cost
    assert torch.allclose(a.x, b.x, atol=1e-9)


def test_lasso_drops_parameters_without_error(robot, generator):
    """Errors only on a few parameters: LASSO keeps (at least) those and refits without bias."""
    model = ErrorModel(robot)
    x_true = model.nominal_vector()
    for name, value in (("a3", 8e-4), ("theta4", math.radians(0.1)), ("d4", -6e-4)):
        x_true[model.layout.index(name)] += value
    q = robot.sample_joints(150, generator)
    data = Measurements(q=q, position=model.tcp_position(q, x_true) + 1e-5 * torch.randn(150, 3, generator=generator, dtype=torch.float64))
    result = calibrate(robot, data, identifier=IDENTIFIERS["lasso"]())
    kept = set(result.free_names)
    assert {"a3", "theta4", "d4"} <= kept
    assert len([n for n in kept if not n.startswith(("base_", "tool_"))]) < 16
    for name, value in (("a3", 8e-4), ("d4", -6e-4)):
        i = model.layout.index(name)
        assert abs(float(result.x[i] - model.nominal_vector()[i]) - value) < 3e-5
