"""Deformed kinematics and the axis-based re-derivation against closed forms."""

from __future__ import annotations

import math

import pytest
import torch

from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import RobotModel
from torchcal.stiffness.deformed import (
    deformed_joint_poses,
    deformed_tcp_pose,
    loaded_tcp_pose,
    rederive_parameters,
)
from torchcal.stiffness.vjm import classic_compliance, joint_deformations

D = math.pi / 180

# Rows [alpha, a, beta, theta, d]. Conditions for an exact round trip of the axis method:
# row 1 without alpha/a/beta (frame 0 on axis 1), a > 0 where a common normal exists, d = 0 on
# the first axis of a parallel pair (Hayati origin), theta = 0 on the last row (its x axis is the
# previous one's, the flange takes the rest).
DH_LIKE = [
    [0.0, 0.0, 0.0, 10 * D, 0.40],
    [-90 * D, 0.025, 0.0, -80 * D, 0.03],
    [70 * D, 0.455, 0.0, 5 * D, -0.02],
    [-90 * D, 0.035, 0.0, 12 * D, 0.42],
    [90 * D, 0.01, 0.0, -7 * D, 0.05],
    [-90 * D, 0.02, 0.0, 0.0, 0.08],
]
PARALLEL = [
    [0.0, 0.0, 0.0, 3 * D, 0.40],
    [-90 * D, 0.025, 0.0, -90 * D, 0.0],
    [0.0, 0.455, 0.4 * D, 4 * D, 0.015],  # axes 2 and 3 parallel, axis 3 tilted by beta
    [-90 * D, 0.035, 0.0, -6 * D, 0.42],
    [90 * D, 0.012, 0.0, 8 * D, 0.0],
    [-90 * D, 0.01, 0.0, 0.0, 0.08],
]


def _model(rows) -> tuple[ErrorModel, torch.Tensor]:
    n = len(rows)
    robot = RobotModel(
        name="table",
        joint_names=tuple(f"joint{i}" for i in range(1, n + 1)),
        table=torch.tensor(rows, dtype=torch.float64),
        joint_limits=torch.tensor([[-math.pi, math.pi]] * n, dtype=torch.float64),
        tool=torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64),
    )
    model = ErrorModel(robot)
    return model, model.nominal_vector()


def _chain_fk(frames, q):
    """``T_base_flange`` of an axis-method result at joints ``q`` ``(B, N)``."""
    m, x = _model(frames.table.tolist())
    rot_pos = m.base_flange_pose(q, x)
    return frames.T_base_0 @ rot_pos @ frames.T_n_flange


@pytest.mark.parametrize("rows", [DH_LIKE, PARALLEL], ids=["dh-like", "parallel-beta"])
def test_rederivation_recovers_the_known_table(rows):
    model, x = _model(rows)
    zero = torch.zeros(len(rows), 6, dtype=torch.float64)
    frames = rederive_parameters(model, x, zero)
    torch.testing.assert_close(frames.table, torch.tensor(rows, dtype=torch.float64), atol=1e-9, rtol=0)
    torch.testing.assert_close(frames.T_base_0, torch.eye(4, dtype=torch.float64), atol=1e-9, rtol=0)
    torch.testing.assert_close(frames.T_n_flange, torch.eye(4, dtype=torch.float64), atol=1e-9, rtol=0)


@pytest.mark.parametrize("rows", [DH_LIKE, PARALLEL], ids=["dh-like", "parallel-beta"])
def test_spring_about_or_along_a_joint_axis_is_a_parameter_change(rows):
    """Closed form: D_i = Rz(e) adds e to theta_i; D_i = Tz(e) adds e to d_i (non-parallel pair)."""
    model, x = _model(rows)
    n = len(rows)
    parallel_first = {1} if rows is PARALLEL else set()  # 0-based index of axis 2
    e = 2e-3
    for i in range(n - 1):
        expected = torch.tensor(rows, dtype=torch.float64)
        theta = torch.zeros(n, 6, dtype=torch.float64)
        theta[i, 5] = e
        expected[i, 3] += e
        if i not in parallel_first:
            theta[i, 2] = e
            expected[i, 4] += e
        else:
            # Hayati: frame i stays where the previous normal arrives; axis i+1 (tilted by
            # beta) slides along z_i, so the normal meets it e*tan(beta) closer and frame i+1
            # sits e/cos(beta) further along it.
            theta[i, 2] = e
            beta = rows[i + 1][2]
            expected[i + 1, 1] -= e * math.tan(beta)
            expected[i + 1, 4] += e / math.cos(beta)
        frames = rederive_parameters(model, x, theta)
        torch.testing.assert_close(frames.table, expected, atol=1e-9, rtol=0)


@pytest.mark.parametrize("rows", [DH_LIKE, PARALLEL], ids=["dh-like", "parallel-beta"])
def test_rederived_chain_reproduces_the_deformed_chain_everywhere(rows):
    model, x = _model(rows)
    gen = torch.Generator().manual_seed(5)
    n = len(rows)
    theta = torch.randn(n, 6, generator=gen, dtype=torch.float64) * torch.tensor([2e-4] * 3 + [2e-3] * 3)
    frames = rederive_parameters(model, x, theta)
    q = (torch.rand(20, n, generator=gen, dtype=torch.float64) - 0.5) * 2 * math.pi
    _, flange = deformed_joint_poses(model, q, x, theta.expand(20, n, 6))
    torch.testing.assert_close(_chain_fk(frames, q), flange, atol=1e-9, rtol=0)
    if rows is PARALLEL:
        # The tilt of the parallel pair went into beta, not into an enormous d.
        assert abs(float(frames.table[2, 2])) > 0 and abs(float(frames.table[1, 4])) < 1e-9
        assert float(frames.table[:, 4].abs().max()) < 1.0


def test_a_tight_hayati_threshold_turns_an_elastic_tilt_into_a_huge_offset():
    """Why the default is 2 deg: with 1e-5 rad, a 1e-3 rad tilt of axes 2/3 gives d ~ a / tilt."""
    rows = [r[:] for r in PARALLEL]
    rows[2][2] = 0.0
    model, x = _model(rows)
    theta = torch.zeros(6, 6, dtype=torch.float64)
    theta[1, 4] = 1e-3  # joint-2 spring bends about its y axis: axis 3 tilts towards axis 2
    default = rederive_parameters(model, x, theta)
    tight = rederive_parameters(model, x, theta, parallel_threshold_rad=1e-5)
    assert float(default.table[:, 4].abs().max()) < 1.0
    assert float(tight.table[:, 4].abs().max()) > 100.0
    q = torch.zeros(1, 6, dtype=torch.float64)
    for frames in (default, tight):  # both describe the same chain; only conditioning differs
        _, flange = deformed_joint_poses(model, q, x, theta.expand(1, 6, 6))
        torch.testing.assert_close(_chain_fk(frames, q), flange, atol=1e-7, rtol=0)


def test_spring_equilibrium_converges_and_first_iteration_is_vjm(robot):
    model = ErrorModel(robot)
    x = model.nominal_vector()
    gen = torch.Generator().manual_seed(2)
    q = robot.sample_joints(8, gen)
    w = torch.randn(8, 6, generator=gen, dtype=torch.float64) * torch.tensor([300.0] * 3 + [30.0] * 3)
    c = classic_compliance(torch.tensor([1e5, 1e5, 1e5, 1e4, 1e4, 1e4], dtype=torch.float64))
    one, theta1 = loaded_tcp_pose(model, q, x, c, w, iterations=1)
    torch.testing.assert_close(theta1, joint_deformations(model, q, x, c, w))
    torch.testing.assert_close(one, deformed_tcp_pose(model, q, x, theta1))
    p4, _ = loaded_tcp_pose(model, q, x, c, w, iterations=4)
    p5, _ = loaded_tcp_pose(model, q, x, c, w, iterations=5)
    assert float((p4[:, :3, 3] - p5[:, :3, 3]).norm(dim=-1).max()) < 1e-10
    # The equilibrium on the deformed structure differs from the first-order one, slightly.
    gap = float((p4[:, :3, 3] - one[:, :3, 3]).norm(dim=-1).max())
    defl = float((one[:, :3, 3] - model.tcp_position(q, x)).norm(dim=-1).max())
    assert 0 < gap < 0.05 * defl
