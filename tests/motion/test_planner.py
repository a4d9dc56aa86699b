"""The planner against independent truth: a textbook MDH product in NumPy (not torchcal's chain)
for the TCP, finite differences of the written samples for speeds and accelerations."""

import math

import numpy as np
import pytest
import torch

from torchcal.motion.planner import PlanOptions, plan_motion
from torchcal.motion.priority import TcpKinematics
from torchcal.motion.scenario import perturbed_parameters, singular_line

DEG = math.pi / 180.0
TOL_MM = 0.005


def _kin(model, x):
    return TcpKinematics(model.table(x), model.T_base_0, model.T_n_flange @ model.flange_from_tool(x))


def _line_error_mm(points: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Distance (mm) of points (K, 3) m from the segment start-end: independent of any time law."""
    u = end - start
    lam = np.clip((points - start) @ u / (u @ u), 0.0, 1.0)
    return np.linalg.norm(points - (start + lam[:, None] * u), axis=-1) * 1e3


def _rotation_deg(r: np.ndarray, target: np.ndarray) -> np.ndarray:
    cos = np.clip((np.trace(target @ np.swapaxes(r, -1, -2), axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def _rates(q: np.ndarray, dt: float):
    padded = np.concatenate([q[:1], q, q[-1:]])
    return np.abs(np.diff(q, axis=0)).max(0) / dt / DEG, np.abs(np.diff(padded, 2, axis=0)).max(0) / dt**2 / DEG


@pytest.fixture(scope="module")
def wrist_line(model, x_nom):
    return singular_line(model, x_nom, length_m=0.4, spin_rad=0.0)


@pytest.fixture(scope="module")
def wrist_motion(robot, model, x_nom, wrist_line):
    poses = torch.stack([wrist_line.path.start, wrist_line.path.end])
    options = PlanOptions(start=(wrist_line.q_start / DEG).tolist())
    return plan_motion(_kin(model, x_nom), robot, poses, options), poses.numpy()


def test_wrist_singularity_line_acceptance(wrist_motion, mdh_fk):
    planned, poses = wrist_motion
    tcp = mdh_fk(planned.q)
    q5 = planned.q[:, 4] / DEG
    assert q5[0] > 20 and q5[-1] < -20 and np.abs(q5).min() < 0.5  # it really passes q5 = 0
    assert planned.sigma_orientation.min() < 1e-3
    line = _line_error_mm(tcp[:, :3, 3], poses[0, :3, 3], poses[1, :3, 3])
    assert line.max() <= TOL_MM
    assert np.linalg.norm(tcp[0, :3, 3] - poses[0, :3, 3]) * 1e3 <= TOL_MM
    assert np.linalg.norm(tcp[-1, :3, 3] - poses[1, :3, 3]) * 1e3 <= TOL_MM
    dt = 0.004
    np.testing.assert_allclose(np.diff(planned.t), dt, rtol=0, atol=1e-12)
    speed, accel = _rates(planned.q, dt)
    assert speed.max() <= 180.0 and accel.max() <= 3000.0
    assert planned.t[-1] <= 2.0
    orientation = _rotation_deg(tcp[:, :3, :3], poses[0, :3, :3])  # constant orientation along the line
    assert orientation.max() < 0.05  # the orientation yields, a little, near q5 = 0
    # the TCP speed reaches the requested 250 mm/s (it is not slowed down needlessly)
    tcp_speed = np.linalg.norm(np.diff(tcp[:, :3, 3], axis=0), axis=-1) / dt * 1e3
    assert 245.0 <= tcp_speed.max() <= 250.0 + 1e-6


def test_regular_line_holds_position_and_orientation(robot, model, x_nom, mdh_fk):
    line = singular_line(model, x_nom, q_singular=torch.tensor([10, -80, 10, 0, 60, 20], dtype=torch.float64) * DEG,
                         length_m=0.4, spin_rad=0.3)
    poses = torch.stack([line.path.start, line.path.end])
    planned = plan_motion(_kin(model, x_nom), robot, poses, PlanOptions(start=(line.q_start / DEG).tolist()))
    tcp = mdh_fk(planned.q)
    assert planned.sigma_orientation.min() > 0.3  # away from singularities
    assert np.linalg.norm(tcp[:, :3, 3] - planned.targets[:, :3, 3], axis=-1).max() * 1e3 <= TOL_MM
    assert _rotation_deg(tcp[:, :3, :3], planned.targets[:, :3, :3]).max() <= 0.001
    assert _line_error_mm(tcp[:, :3, 3], poses[0, :3, 3].numpy(), poses[1, :3, 3].numpy()).max() <= TOL_MM


def test_line_missing_the_singularity_yields_orientation_within_limits(robot, model, wrist_line):
    """The twin's true robot on the nominal line: it passes q5 = 0 at a small distance, where the exact
    solution would turn q4 and q6 by ~180 deg; position first keeps the path, the orientation yields."""
    x_true = perturbed_parameters(model, 0)
    poses = torch.stack([wrist_line.path.start, wrist_line.path.end])
    kin = _kin(model, x_true)
    planned = plan_motion(kin, robot, poses, PlanOptions(start=(wrist_line.q_start / DEG).tolist()))
    pose = kin.pose(torch.from_numpy(planned.q)).numpy()
    assert np.linalg.norm(pose[:, :3, 3] - planned.targets[:, :3, 3], axis=-1).max() * 1e3 <= TOL_MM
    orientation = _rotation_deg(pose[:, :3, :3], planned.targets[:, :3, :3])
    assert 0.05 < orientation.max() < 2.0
    speed, accel = _rates(planned.q, 0.004)
    assert np.all(speed <= planned.joint_speed / DEG * (1 + 1e-9))
    assert np.all(accel <= planned.joint_accel / DEG * (1 + 1e-9))
    assert accel.max() > 0.8 * 3000  # the wrist's turn is what the time law had to slow down for


def test_joint_limits_slow_the_motion_down_on_the_same_path(robot, model, x_nom, wrist_line, wrist_motion, mdh_fk):
    poses = torch.stack([wrist_line.path.start, wrist_line.path.end])
    options = PlanOptions(start=(wrist_line.q_start / DEG).tolist(), joint_speed=[20.0] * 6, joint_accel=[200.0] * 6)
    slow = plan_motion(_kin(model, x_nom), robot, poses, options)
    speed, accel = _rates(slow.q, 0.004)
    assert speed.max() <= 20.0 and accel.max() <= 200.0
    assert slow.t[-1] > 1.5 * wrist_motion[0].t[-1]
    tcp = mdh_fk(slow.q)
    assert _line_error_mm(tcp[:, :3, 3], poses[0, :3, 3].numpy(), poses[1, :3, 3].numpy()).max() <= TOL_MM


def test_corner_waypoint_stops_with_continuous_velocity(robot, model, x_nom, mdh_fk):
    q_mid = torch.tensor([0, -70, 20, 10, 50, 0], dtype=torch.float64) * DEG
    first = model.tcp_pose(q_mid, x_nom)
    poses = first.expand(3, 4, 4).clone()
    poses[1, :3, 3] += torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64)
    poses[2, :3, 3] += torch.tensor([0.1, 0.1, 0.0], dtype=torch.float64)
    planned = plan_motion(_kin(model, x_nom), robot, poses, PlanOptions(start=(q_mid / DEG).tolist(), dt=0.002))
    tcp = mdh_fk(planned.q)[:, :3, 3]
    first_leg = planned.segment == 0
    assert _line_error_mm(tcp[first_leg], poses[0, :3, 3].numpy(), poses[1, :3, 3].numpy()).max() <= TOL_MM
    assert _line_error_mm(tcp[~first_leg], poses[1, :3, 3].numpy(), poses[2, :3, 3].numpy()).max() <= TOL_MM
    corner = int(np.argmin(np.linalg.norm(tcp - poses[1, :3, 3].numpy(), axis=-1)))
    tcp_speed = np.linalg.norm(np.diff(tcp, axis=0), axis=-1) / 0.002 * 1e3
    assert tcp_speed[corner - 1 : corner + 1].max() < 10.0  # it (nearly) stops at the corner sample
    _, accel = _rates(planned.q, 0.002)
    assert accel.max() <= 3000.0  # continuous joint velocity: bounded second differences through the stop
