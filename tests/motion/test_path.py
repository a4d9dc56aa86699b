
import pytest
import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics import transforms as tf
from torchcal.motion.path import ArcPath, CartesianLimits, LinePath, slerp


def _pose(rotvec, p):
    return tf.homogeneous(tf.so3_exp(torch.tensor(rotvec, dtype=torch.float64)), torch.tensor(p, dtype=torch.float64))


START = _pose([0.1, -0.2, 0.3], [0.5, 0.1, 0.6])
END = _pose([-0.3, 0.4, 0.2], [0.7, -0.2, 0.4])


def test_slerp_endpoints_and_constant_rate():
    lam = torch.linspace(0, 1, 11, dtype=torch.float64)
    r = slerp(START[:3, :3], END[:3, :3], lam)
    torch.testing.assert_close(r[0], START[:3, :3])
    torch.testing.assert_close(r[-1], END[:3, :3])
    steps = tf.so3_log(r[1:] @ r[:-1].transpose(-1, -2))
    torch.testing.assert_close(steps, steps[:1].expand_as(steps))  # same axis and angle each step


@pytest.mark.parametrize("make", [lambda: LinePath(START, END), lambda: ArcPath(START, torch.tensor([0.8, 0.1, 0.5], dtype=torch.float64), END)])
def test_tangent_is_derivative_of_pose(make):
    path = make()
    lam = torch.linspace(0.05, 0.95, 7, dtype=torch.float64)
    h = 1e-6
    plus, minus = path.poses(lam + h), path.poses(lam - h)
    dp = (plus[:, :3, 3] - minus[:, :3, 3]) / (2 * h)
    dw = tf.so3_log(plus[:, :3, :3] @ minus[:, :3, :3].transpose(-1, -2)) / (2 * h)
    torch.testing.assert_close(path.tangent(lam), torch.cat([dp, dw], -1), atol=1e-7, rtol=1e-7)
    torch.testing.assert_close(path.poses(torch.tensor(0.0, dtype=torch.float64)), START)
    torch.testing.assert_close(path.poses(torch.tensor(1.0, dtype=torch.float64)), END)


def test_arc_geometry_passes_via_point():
    via = torch.tensor([0.8, 0.1, 0.5], dtype=torch.float64)
    arc = ArcPath(START, via, END)
    lam = torch.linspace(0, 1, 2001, dtype=torch.float64)
    p, _ = arc.positions(lam)
    radius = (p - arc.center).norm(dim=-1)
    torch.testing.assert_close(radius, torch.full_like(radius, arc.radius))
    assert float((p - via).norm(dim=-1).min()) < arc.length / 2000
    chord = torch.diff(p, dim=0).norm(dim=-1).sum()
    assert float(chord) == pytest.approx(arc.length, rel=1e-6)
    with pytest.raises(ModelError):
        ArcPath(START, 0.5 * (START[:3, 3] + END[:3, 3]), END)


def test_sampling_respects_cartesian_limits_and_rate():
    limits = CartesianLimits(linear_speed=0.2, linear_accel=1.0, linear_jerk=10.0, angular_speed=0.5, angular_accel=2.0, angular_jerk=20.0)
    path = LinePath(START, END)
    for rate in (250.0, 1000.0):
        traj = path.sample("scurve", limits, rate)
        assert float(torch.diff(traj.t).max()) == pytest.approx(1.0 / rate)
        torch.testing.assert_close(traj.poses[-1], END)
        assert float(traj.twists[:, :3].norm(dim=-1).max()) <= 0.2 * (1 + 1e-9)
        assert float(traj.twists[:, 3:].norm(dim=-1).max()) <= 0.5 * (1 + 1e-9)
    with pytest.raises(ModelError):
        LinePath(START, START).profile()
