"""The 'before' of every report: the nominal robot with its instrument frame and tool fitted."""

from __future__ import annotations

from dataclasses import replace

import torch

from torchcal.data.measurements import Measurements
from torchcal.kinematics import transforms as tf
from torchcal.stages.geometry import nominal_errors, nominal_fit, registered_errors


def test_nominal_fit_recovers_frame_and_tool(robot):
    """Points of the nominal robot with a tool 6 mm off its nominal: frame alone leaves error, frame + tool none."""
    q = robot.sample_joints(60, torch.Generator().manual_seed(3))
    true_tool = robot.tool + torch.tensor([0.004, -0.003, 0.002], dtype=torch.float64)
    frame = tf.homogeneous(tf.so3_exp(torch.tensor([0.3, -0.2, 1.1], dtype=torch.float64)),
                           torch.tensor([2.0, -0.5, 0.3], dtype=torch.float64))
    base = replace(robot, tool=true_tool).tcp_position(q)
    data = Measurements(q=q, position=base @ frame[:3, :3].T + frame[:3, 3])
    errors, transform, tool = nominal_fit(robot, data)
    assert float(errors.norm(dim=-1).max()) < 1e-9
    assert torch.allclose(transform, frame, atol=1e-9) and torch.allclose(tool, true_tool, atol=1e-10)
    frame_only = registered_errors(robot.tcp_position(q), data.position).norm(dim=-1)
    assert float(frame_only.pow(2).mean().sqrt()) > 1e-3  # > 1 mm: what a frame-only baseline overstates
    assert torch.equal(nominal_errors(robot, data), errors)
