import math

import torch

from torchcal.motion.metrics import acceleration_steps, path_errors, summarize, velocity_steps


def test_velocity_and_acceleration_steps_closed_form():
    dt = 0.004
    t = torch.arange(100, dtype=torch.float64) * dt
    qdot = torch.stack([2.0 * t, torch.where(t < 0.2, 0.0, 1.0)], -1)  # a ramp and a step
    steps = velocity_steps(qdot).max(0).values
    torch.testing.assert_close(steps, torch.tensor([2.0 * dt, 1.0], dtype=torch.float64))
    acc = acceleration_steps(qdot, dt).max(0).values
    assert float(acc[0]) < 1e-9 and math.isclose(float(acc[1]), 1.0 / dt)


def test_path_errors_and_summary(model, x_nom):
    q = model.robot.sample_joints(20, torch.Generator().manual_seed(0), margin=0.2)
    target = model.tcp_pose(q, x_nom)
    pos, rot = path_errors(model, x_nom, q, target)
    assert float(pos.max()) < 1e-12 and float(rot.max()) < 1e-7
    moved = target.clone()
    moved[:, 0, 3] += 1e-3
    pos, _ = path_errors(model, x_nom, q, moved)
    torch.testing.assert_close(pos, torch.full_like(pos, 1e-3))
    sigma = torch.linspace(0, 1, 20, dtype=torch.float64)
    m = summarize(model, x_nom, q, torch.zeros_like(q), moved, sigma, 0.1, torch.ones(6, dtype=torch.float64), 0.004)
    error_mm = m.max_position_error_outside_mm
    assert math.isclose(error_mm, 1.0, rel_tol=1e-9) and m.samples_inside == 2 and m.peak_speed_ratio == 0.0
