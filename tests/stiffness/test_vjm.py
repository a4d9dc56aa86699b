"""VJM Jacobian and deflection against finite differences of the deformed chain."""

from __future__ import annotations

import math

import pytest
import torch

from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.stiffness.deformed import deformed_tcp_pose
from torchcal.stiffness.vjm import (
    cartesian_compliance,
    classic_compliance,
    compliance_from_stiffness,
    deflection,
    joint_deformations,
    spring_names,
    virtual_joint_jacobian,
    wrench_in_instrument,
)


def _pose_difference(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``[p_a - p_b; log(R_a R_b^T)]``, instrument frame."""
    return torch.cat([a[..., :3, 3] - b[..., :3, 3], tf.so3_log(a[..., :3, :3] @ b[..., :3, :3].transpose(-1, -2))], -1)


@pytest.fixture
def setup(robot):
    gen = torch.Generator().manual_seed(3)
    T = tf.homogeneous(tf.so3_exp(torch.tensor([0.3, -1.1, 0.7], dtype=torch.float64)), torch.tensor([2.0, -1.0, 0.3], dtype=torch.float64))
    model = ErrorModel(robot, T_instrument_base=T)
    x = model.nominal_vector()
    x[model.layout.tool_slice] = torch.tensor([0.03, -0.02, 0.12, 0.1, -0.2, 0.3], dtype=torch.float64)
    q = robot.sample_joints(5, gen)
    stiffness = torch.exp(torch.rand(robot.dof, 6, generator=gen, dtype=torch.float64) * 4 + 10)
    return model, x, q, compliance_from_stiffness(stiffness), gen


def test_jacobian_matches_finite_differences_of_the_deformed_chain(setup):
    model, x, q, _, _ = setup
    pose, jac = virtual_joint_jacobian(model, q, x)
    n = model.robot.dof
    assert jac.shape == (5, 6, 6 * n)
    h = 1e-6
    for col in range(6 * n):
        theta = torch.zeros(5, n * 6, dtype=torch.float64)
        theta[:, col] = h
        plus = deformed_tcp_pose(model, q, x, theta.reshape(5, n, 6))
        minus = deformed_tcp_pose(model, q, x, (-theta).reshape(5, n, 6))
        fd = (_pose_difference(plus, pose) - _pose_difference(minus, pose)) / (2 * h)
        torch.testing.assert_close(jac[..., col], fd, atol=1e-8, rtol=0)


def test_deflection_is_the_derivative_of_the_loaded_chain(setup):
    model, x, q, compliance, gen = setup
    wrench = torch.randn(5, 6, generator=gen, dtype=torch.float64) * torch.tensor([200, 200, 200, 20, 20, 20])
    dx = deflection(model, q, x, compliance, wrench)
    theta = joint_deformations(model, q, x, compliance, wrench)
    pose = model.tcp_pose(q, x)
    eps = 1e-4
    fd = (_pose_difference(deformed_tcp_pose(model, q, x, eps * theta), pose) - _pose_difference(deformed_tcp_pose(model, q, x, -eps * theta), pose)) / (2 * eps)
    torch.testing.assert_close(dx, fd, atol=1e-12, rtol=1e-7)
    # At the real (small) load the first-order law is within a few 1e-3 of the exact chain.
    exact = _pose_difference(deformed_tcp_pose(model, q, x, theta), pose)
    assert float((exact - dx).norm(dim=-1).max()) < 0.01 * float(dx.norm(dim=-1).max())


def test_classic_model_equals_geometric_jacobian_formula(setup, robot):
    model, x, q, _, gen = setup
    k = torch.tensor([4e5, 3e5, 2e5, 5e4, 4e4, 3e4], dtype=torch.float64)
    wrench_tool = torch.randn(5, 6, generator=gen, dtype=torch.float64) * 100
    pose, jac = geometric_jacobian(model, q, x)
    w = wrench_in_instrument(wrench_tool, pose, "tool")
    expected = (jac @ torch.diag(1 / k) @ jac.transpose(-1, -2) @ w.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(deflection(model, q, x, classic_compliance(k), wrench_tool), expected, atol=1e-14, rtol=1e-10)
    torch.testing.assert_close(deflection(model, q, x, classic_compliance(k), w, wrench_frame="instrument"), expected, atol=1e-14, rtol=1e-10)


def test_cartesian_compliance_is_symmetric_and_consistent(setup):
    model, x, q, compliance, gen = setup
    c = cartesian_compliance(model, q, x, compliance)
    torch.testing.assert_close(c, c.transpose(-1, -2), atol=1e-18, rtol=1e-12)
    assert bool((torch.linalg.eigvalsh(c) > -1e-15).all())
    w = torch.randn(5, 6, generator=gen, dtype=torch.float64)
    torch.testing.assert_close((c @ w.unsqueeze(-1)).squeeze(-1), deflection(model, q, x, compliance, w, wrench_frame="instrument"))


def test_full_symmetric_compliance_and_batching(setup):
    model, x, q, _, gen = setup
    n = model.robot.dof
    a = torch.randn(n, 6, 6, generator=gen, dtype=torch.float64) * 1e-6
    full = a @ a.transpose(-1, -2)
    qb = q[:4].reshape(2, 2, n)
    w = torch.randn(2, 2, 6, generator=gen, dtype=torch.float64)
    batched = deflection(model, qb, x, full, w)
    flat = deflection(model, qb.reshape(4, n), x, full, w.reshape(4, 6))
    assert batched.shape == (2, 2, 6)
    torch.testing.assert_close(batched.reshape(4, 6), flat)
    # Superposition: the deflection is linear in the compliance.
    torch.testing.assert_close(deflection(model, qb, x, 2 * full, w), 2 * batched)


def test_names_and_rigid_entries():
    names = spring_names(6)
    assert len(names) == 36 and names[0] == "k_j1_tx" and names[-1] == "k_j6_rz"
    c = compliance_from_stiffness(torch.tensor([[math.inf] * 5 + [2.0]]))
    assert c.shape == (1, 6, 6) and float(c.sum()) == 0.5
