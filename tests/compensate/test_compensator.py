"""The compensator and monitor graphs against independent kinematics (torch side only)."""

import math

import pytest
import torch

from torchcal.compensate.compensator import CompensatorGraph, MonitorGraph
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import pose_error
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.model_store import load_model

from known_cases import KnownResidual, nominal_tcp_pose, residual_value


def regular_poses(stored, n, seed, min_singular=0.05):
    """Random poses within the limits whose Jacobian is far from singular."""
    q = stored.robot.sample_joints(4 * n, torch.Generator().manual_seed(seed))
    _, jac = geometric_jacobian(ErrorModel(stored.robot), q, stored.x)
    return q[torch.linalg.svdvals(jac)[:, -1] > min_singular][:n]


@pytest.fixture(scope="module")
def stored(model_dir):
    return load_model(model_dir)


def test_compensator_reaches_the_nominal_pose_with_the_calibrated_model(stored):
    q = regular_poses(stored, 500, seed=1)
    base_model = ErrorModel(stored.robot)  # identity instrument frame: calibrated base frame
    target = nominal_tcp_pose(stored.robot, q)
    before = pose_error(target, base_model.tcp_pose(q, stored.x))
    assert before[:, :3].norm(dim=-1).median() > 2e-4  # there is something to correct
    with torch.no_grad():
        q_c = CompensatorGraph(stored.model, stored.x)(q)
    after = pose_error(target, base_model.tcp_pose(q_c, stored.x))
    assert after[:, :3].norm(dim=-1).max() < 1e-9  # m
    assert after[:, 3:].norm(dim=-1).max() < 1e-9  # rad


def test_residual_head_is_compensated_with_the_patent_sign(stored):
    """p_cal(q_c) + r(q_c) = p_t, and p_nom(q_c) = p_t - dp(q_c) with dp the monitor output."""
    q = regular_poses(stored, 300, seed=2)
    base_model = ErrorModel(stored.robot)
    target = nominal_tcp_pose(stored.robot, q)
    with torch.no_grad():
        q_c = CompensatorGraph(stored.model, stored.x, KnownResidual())(q)
        dp = MonitorGraph(stored.model, stored.x, KnownResidual())(q_c)
    reached = base_model.tcp_position(q_c, stored.x) + residual_value(q_c)
    assert (reached - target[:, :3, 3]).norm(dim=-1).max() < 1e-9
    # T_c = T_t - dT: the nominal robot at the corrected command sits at the target minus the error
    assert (stored.robot.tcp_position(q_c) - (target[:, :3, 3] - dp)).norm(dim=-1).max() < 1e-9
    # the patents' single evaluation of dT at q_t agrees to second order only
    with torch.no_grad():
        dp_t = MonitorGraph(stored.model, stored.x, KnownResidual())(q)
    assert ((dp - dp_t).norm(dim=-1) < 0.05 * dp_t.norm(dim=-1)).all()


def test_monitor_is_calibrated_minus_nominal(stored):
    q = stored.robot.sample_joints(1000, torch.Generator().manual_seed(3))
    expected = ErrorModel(stored.robot).tcp_position(q, stored.x) + residual_value(q) - stored.robot.tcp_position(q)
    with torch.no_grad():
        got = MonitorGraph(stored.model, stored.x, KnownResidual())(q)
        got32 = MonitorGraph(stored.model, stored.x, KnownResidual(), dtype=torch.float32)(q.float())
    assert (got - expected).abs().max() < 1e-14
    assert (got32.double() - expected).norm(dim=-1).max() < 1e-6  # m


def test_damping_bounds_the_step_at_a_wrist_singularity(stored):
    q = regular_poses(stored, 50, seed=4)
    q[:, 4] = 0.0  # q5 = 0: axes 4 and 6 align
    with torch.no_grad():
        q_c = CompensatorGraph(stored.model, stored.x)(q)
    assert torch.isfinite(q_c).all()
    # without damping the wrist would spin; the damped step stays a few degrees at most
    assert (q_c - q).abs().max() < math.radians(20)


def test_iteration_count_is_what_converges(stored):
    """The default count reaches 1e-9 m where one step fewer does not (the docstring's claim)."""
    q = regular_poses(stored, 500, seed=5)
    target = nominal_tcp_pose(stored.robot, q)[:, :3, 3]
    errors = {}
    for n in (CompensatorGraph(stored.model, stored.x).iterations - 1, CompensatorGraph(stored.model, stored.x).iterations):
        with torch.no_grad():
            q_c = CompensatorGraph(stored.model, stored.x, iterations=n)(q)
        errors[n] = (ErrorModel(stored.robot).tcp_position(q_c, stored.x) - target).norm(dim=-1).max()
    low, high = sorted(errors)
    assert errors[high] < 1e-9 < errors[low]
