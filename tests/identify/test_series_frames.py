"""Each later series at its own registered frame (identify.series_frames): checked against the twin's truth
and finite differences."""

from __future__ import annotations

import torch

from torchcal.data.measurements import Measurements
from torchcal.data.series import pool_series
from torchcal.identify.problem import CalibrationProblem
from torchcal.identify.series_frames import held_out_errors, per_series_registered
from torchcal.sim.twin import Twin, TwinConfig


def _two_placements(n: int = 40):
    twin = Twin.create(TwinConfig(seed=2))
    moved = twin.changed(base_x=0.5, base_y=0.3, base_rz=0.4, base_ry=0.02)
    gen = torch.Generator().manual_seed(1)
    qa, qb = twin.robot.sample_joints(n, gen), twin.robot.sample_joints(n, gen)
    # noise-free: at the true parameters every series is explained once its frame is registered
    a = Measurements(q=qa, position=twin.true_positions(qa))
    b = Measurements(q=qb, position=moved.true_positions(qb))
    return twin, pool_series([a, b])


def test_true_parameters_leave_no_residual_once_each_frame_is_registered():
    twin, pooled = _two_placements()
    problem = CalibrationProblem(twin.model, pooled, twin.model.default_active().nonzero().squeeze(-1))
    raw = pooled.position - twin.model.tcp_position(pooled.q, twin.x_true)
    assert raw[40:].norm(dim=-1).min() > 0.1  # the second series is metres off in the first one's frame
    assert problem.residuals(twin.x_true).abs().max() < 1e-9


def test_projected_jacobian_is_the_derivative_of_the_registered_residual_at_a_zero_residual():
    # at zero residual Kaufman's projected Jacobian is the exact derivative of the variable-projection residual
    twin, pooled = _two_placements()
    free = twin.model.default_active().nonzero().squeeze(-1)
    problem = CalibrationProblem(twin.model, pooled, free)
    _, jac = problem.jacobian(twin.x_true)
    step = 1e-7
    for k in (0, 5, 9, 14, len(free) - 1):
        x_plus, x_minus = twin.x_true.clone(), twin.x_true.clone()
        x_plus[free[k]] += step
        x_minus[free[k]] -= step
        numeric = (problem.residuals(x_plus) - problem.residuals(x_minus)) / (2 * step)
        assert torch.allclose(jac[:, k], numeric, atol=1e-6 * max(1.0, float(numeric.abs().max()))), k


def test_a_single_series_is_untouched():
    _, pooled = _two_placements()
    r = torch.randn(len(pooled) * 3, dtype=torch.float64)
    single = Measurements(q=pooled.q, position=pooled.position)
    assert torch.equal(per_series_registered(single, r)[0], r)


def test_held_out_poses_of_a_later_series_are_scored_in_the_frame_of_its_training_poses():
    twin, pooled = _two_placements()
    train, test = pooled.subset(list(range(30)) + list(range(40, 70))), pooled.subset(list(range(30, 40)) + list(range(70, 80)))

    def predict(q):
        return twin.model.tcp_position(q, twin.x_true)

    errors = held_out_errors(predict, train, test)
    assert errors.abs().max() < 1e-9
    # without a frame from the training poses the second series' points would be metres off
    assert (test.position - predict(test.q))[10:].norm(dim=-1).min() > 0.1
