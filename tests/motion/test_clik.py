import dataclasses
import math

import pytest
import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import solve_ik
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.motion.clik import _FixedModel, follow, limit_scale
from torchcal.motion.config import MotionConfig
from torchcal.motion.metrics import path_errors, velocity_steps
from torchcal.motion.scenario import perturbed_parameters, singular_line

DEG = math.pi / 180.0
ACCEPT_M = 0.005e-3
RAW = MotionConfig(enforce_speed_limits=False)


@pytest.fixture(scope="module")
def line(model, x_nom):
    return singular_line(model, x_nom)


@pytest.fixture(scope="module")
def traj(line):
    return line.path.sample(RAW.profile, RAW.limits, RAW.rate_hz)


@pytest.fixture(scope="module")
def twin(model, line):
    """The twin's true robot and its start joints for the line planned with the nominal model."""
    x_true = perturbed_parameters(model, 0)
    return x_true, solve_ik(model, x_true, line.path.start, line.q_start).q


@pytest.fixture(scope="module")
def runs(model, x_nom, line, traj, twin):
    x_true, q0 = twin
    return {
        "nominal": follow(model, x_nom, traj, line.q_start, RAW),
        "dls": follow(model, x_true, traj, q0, RAW),
        "pinv": follow(model, x_true, traj, q0, dataclasses.replace(RAW, method="pinv")),
        "open_loop": follow(model, x_true, traj, q0, dataclasses.replace(RAW, gain=0.0)),
    }


def _errors(model, x, result, traj, eps=RAW.damping_eps):
    pos, rot = path_errors(model, x, result.trajectory.q, traj.poses)
    outside = result.sigma_min >= eps
    return pos, rot, outside


def test_fixed_model_matches_geometric_jacobian(model):
    x = perturbed_parameters(model, 3)
    x[model.layout.base_slice] = torch.tensor([0.1, 0.2, 0.3, 0.1, -0.2, 0.3], dtype=torch.float64)
    q = model.robot.sample_joints(5, torch.Generator().manual_seed(0))
    for a, b in zip(_FixedModel(model, x)(q), geometric_jacobian(model, q, x)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_line_really_crosses_the_wrist_singularity(runs):
    result = runs["nominal"]
    q5 = result.trajectory.q[:, 4]
    assert float(q5[0]) > 10 * DEG and float(q5[-1]) < -10 * DEG
    assert float(result.sigma_min.min()) < 1e-3
    inside = result.sigma_min < RAW.damping_eps
    assert 0 < int(inside.sum()) < len(inside) // 2


def test_clik_tracks_line_away_from_singularity(model, x_nom, runs, traj, twin):
    for result, x in ((runs["nominal"], x_nom), (runs["dls"], twin[0])):
        pos, rot, outside = _errors(model, x, result, traj)
        assert float(pos[outside].max()) <= ACCEPT_M
        assert float(rot[outside].max()) <= 1e-4 * DEG * 10
        assert float(pos.max()) < 10e-3  # bounded inside the neighbourhood


def test_undamped_exceeds_speed_limit_near_singularity_dls_does_not(model, runs):
    limits = RAW.speed_limits(model.robot)
    ratio = {k: (runs[k].trajectory.qdot.abs() / limits).amax(-1) for k in ("dls", "pinv")}
    assert float(ratio["dls"].max()) <= 1.0
    worst = int(ratio["pinv"].argmax())
    assert float(ratio["pinv"][worst]) > 5.0
    assert float(runs["pinv"].sigma_min[worst]) < RAW.damping_eps  # it happens at the singularity
    bound = RAW.velocity_step_bound_deg_s * DEG
    assert float(velocity_steps(runs["dls"].trajectory.qdot).max()) <= bound
    assert float(velocity_steps(runs["pinv"].trajectory.qdot).max()) > 10 * bound


def test_open_loop_drifts_more_than_closed_loop(model, runs, traj, twin):
    closed, _, out_c = _errors(model, twin[0], runs["dls"], traj)
    opened, _, out_o = _errors(model, twin[0], runs["open_loop"], traj)
    assert float(opened[out_o].max()) > 100 * float(closed[out_c].max())
    assert float(opened[-1]) > 1e-4  # 0.1 mm off at the end of the line


def test_calibrated_joints_follow_the_path_nominal_joints_do_not(model, runs, traj, twin):
    x_true = twin[0]
    real_nominal, _ = path_errors(model, x_true, runs["nominal"].trajectory.q, traj.poses)
    real_calibrated, _, outside = _errors(model, x_true, runs["dls"], traj)
    assert float(real_nominal.min()) > 0.5e-3  # the calibration error, everywhere
    assert float(real_calibrated[outside].max()) <= ACCEPT_M


def test_speed_limit_scaling_preserves_direction():
    qdot = torch.tensor([[1.0, -4.0, 0.5], [0.1, 0.1, 0.1]], dtype=torch.float64)
    speed = torch.tensor([2.0, 2.0, 2.0], dtype=torch.float64)
    s, limited = limit_scale(qdot, torch.zeros_like(qdot), 0.004, speed, None)
    torch.testing.assert_close(s, torch.tensor([0.5, 1.0], dtype=torch.float64))
    assert not bool(limited.any())
    bounds = torch.tensor([[-1.0, 1.0]] * 3, dtype=torch.float64)
    q = torch.tensor([[0.0, -0.999, 0.0]], dtype=torch.float64)  # joint 2 has 1 mrad of room
    s, limited = limit_scale(qdot[:1], q, 0.004, speed, bounds)
    assert float(s) == pytest.approx(0.001 / 0.004 / 4.0) and bool(limited)


def test_follow_respects_speed_limits(model, x_nom, line, traj):
    slow = dataclasses.replace(MotionConfig(), speed_limits_deg_s=(8.0,) * 6)
    result = follow(model, x_nom, traj, line.q_start, slow)
    limits = slow.speed_limits(model.robot)
    assert float((result.trajectory.qdot.abs() / limits).max()) <= 1.0 + 1e-12
    assert float(result.scale.min()) < 0.9  # the limit was active


def test_follow_respects_joint_limits(model, x_nom, line, traj):
    robot = model.robot
    limits = robot.joint_limits.clone()
    limits[2, 1] = line.q_start[2] + 5 * DEG  # q3 would need to go further along this line
    tight = ErrorModel(dataclasses.replace(robot, joint_limits=limits))
    result = follow(tight, x_nom, traj, line.q_start, RAW)
    assert float(result.trajectory.q[:, 2].max()) <= float(limits[2, 1]) + 1e-12
    assert bool(result.limited.any())


def test_follow_is_batched(model, x_nom, line):
    short = line.path.sample("trapezoid", None, 250.0)
    q0 = torch.stack([line.q_start, line.q_start + 1e-3])
    both = follow(model, x_nom, short, q0, RAW)
    one = follow(model, x_nom, short, q0[1], RAW)
    torch.testing.assert_close(both.trajectory.q[1], one.trajectory.q)
    assert both.sigma_min.shape == (2, len(short))


def test_config_validation(model, traj, x_nom, line):
    with pytest.raises(ModelError):
        MotionConfig(gain=300.0, rate_hz=250.0)
    with pytest.raises(ModelError):
        MotionConfig(method="jacobian-transpose")
    with pytest.raises(ModelError):
        follow(model, x_nom, traj, line.q_start, MotionConfig(rate_hz=1000.0))
    kr6 = torch.tensor([360.0, 300.0, 360.0, 381.0, 388.0, 615.0], dtype=torch.float64) * DEG
    torch.testing.assert_close(MotionConfig().speed_limits(model.robot), kr6)


def test_follow_with_a_continuous_joint(model, x_nom, line):
    """A joint without limits (``-inf, inf``) is never scaled or clamped and the null-space pull leaves it
    alone: the trajectory stays finite and tracks the path as with finite limits far away."""
    robot = model.robot
    limits = robot.joint_limits.clone()
    limits[5] = torch.tensor([-math.inf, math.inf], dtype=torch.float64)
    free = ErrorModel(dataclasses.replace(robot, joint_limits=limits))
    wide = robot.joint_limits.clone()
    wide[5] = torch.tensor([-1e6, 1e6], dtype=torch.float64)  # as good as no limit: its pull ~1e-12
    far = ErrorModel(dataclasses.replace(robot, joint_limits=wide))
    short = line.path.sample("trapezoid", None, 250.0)
    config = dataclasses.replace(RAW, null_space_gain=1.0)
    a = follow(free, x_nom, short, line.q_start, config)
    b = follow(far, x_nom, short, line.q_start, config)
    assert bool(torch.isfinite(a.trajectory.q).all())
    torch.testing.assert_close(a.trajectory.q, b.trajectory.q, atol=1e-9, rtol=0)
