"""The differentiable error layer: FK, autodiff Jacobians against finite differences, Hayati rule."""

from __future__ import annotations

import math

import torch
from helpers import central_difference

from tests.conftest import perturbed_vector
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import solve_ik
from torchcal.kinematics.joint_jacobian import geometric_jacobian


def test_nominal_vector_reproduces_nominal_fk(robot, generator):
    model = ErrorModel(robot)
    q = robot.sample_joints(50, generator)
    assert torch.allclose(model.tcp_position(q, model.nominal_vector()), robot.tcp_position(q), atol=1e-15)


def test_parameter_jacobian_matches_finite_differences(robot, generator):
    model = ErrorModel(robot)
    x = perturbed_vector(model, generator)
    x[model.layout.base_slice] = torch.tensor([0.3, -0.2, 0.1, 0.2, -0.4, 0.5], dtype=torch.float64)
    x[model.layout.index("beta3")] = 0.001
    q = robot.sample_joints(20, generator)
    _, jac = model.position_jacobian(q, x)
    fd = central_difference(lambda v: model.tcp_position(q, v), x)
    assert float((jac - fd).norm() / fd.norm()) <= 1e-6


def test_pose_jacobian_rotation_rows_match_finite_differences(robot, generator):
    from torchcal.kinematics import transforms as tf

    model = ErrorModel(robot, with_orientation=True)
    x = perturbed_vector(model, generator)
    q = robot.sample_joints(5, generator)
    pose, jac = model.pose_jacobian(q, x)

    def rot_vec(v):
        return tf.so3_log(model.tcp_pose(q, v)[..., :3, :3] @ pose[..., :3, :3].transpose(-1, -2))

    fd = central_difference(rot_vec, x)
    assert float((jac[:, 3:] - fd).norm() / fd.norm()) <= 1e-6


def test_gradients_reach_link_parameters(robot, generator):
    """pytorch-kinematics' analytical-grad FK drops link-parameter gradients; ours must not."""
    model = ErrorModel(robot)
    x = model.nominal_vector().requires_grad_(True)
    q = robot.sample_joints(8, generator)
    model.tcp_position(q, x).sum().backward()
    grad = x.grad[model.layout.index("a3")]
    fd = central_difference(lambda v: model.tcp_position(q, v).sum().reshape(1), x.detach())[0, model.layout.index("a3")]
    assert abs(float(grad) - float(fd)) < 1e-6 * max(1.0, abs(float(fd)))
    assert abs(float(grad)) > 0.1


def test_hayati_rule_switches_d_for_beta_on_parallel_axes(robot):
    model = ErrorModel(robot, parallel_threshold_deg=2.0)
    assert model.parallel_joints == (3,)  # axes 2 and 3 of the twin are parallel
    active = model.default_active()
    names = model.layout.names
    assert active[names.index("beta3")] and not active[names.index("d3")]
    assert not active[names.index("beta4")] and active[names.index("d4")]


def test_geometric_jacobian_and_ik(robot, generator):
    model = ErrorModel(robot)
    x = perturbed_vector(model, generator)
    q = robot.sample_joints(10, generator, margin=math.radians(10))
    pose, jac = geometric_jacobian(model, q, x)
    fd = torch.stack(
        [(model.tcp_position(q + 1e-6 * e, x) - model.tcp_position(q - 1e-6 * e, x)) / 2e-6 for e in torch.eye(6, dtype=torch.float64)],
        -1,
    )
    assert (jac[:, :3] - fd).abs().max() < 1e-8
    result = solve_ik(model, x, pose, q + 0.03)
    assert bool(result.converged.all())
    assert (model.tcp_pose(result.q, x) - pose).abs().max() < 1e-9
