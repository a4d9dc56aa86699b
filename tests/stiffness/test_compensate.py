"""Deflection compensation: identified springs, truth from the twin's deformed chain."""

from __future__ import annotations

import pytest
import torch

from torchcal.kinematics import transforms as tf
from torchcal.stiffness.compensate import DeflectionCompensator, compensate_deflection
from torchcal.stiffness.identify import identify_stiffness


@pytest.fixture(scope="module")
def estimate(rig):
    twin, train, _ = rig
    return identify_stiffness(twin.robot, train, warn=False)


def test_compensation_removes_most_of_the_loaded_error_on_test_poses(rig, estimate):
    twin, _, test = rig
    q, w = test.q, test.wrench
    target = twin.unloaded_pose(q)  # where the command puts the TCP without load
    before = (twin.loaded_pose(q, w)[:, :3, 3] - target[:, :3, 3]).norm(dim=-1)
    result = DeflectionCompensator(estimate.model, estimate.x, estimate.compliance)(q, w)
    assert bool(result.converged.all())
    loaded = twin.loaded_pose(result.q, w)
    after = (loaded[:, :3, 3] - target[:, :3, 3]).norm(dim=-1)
    rms_before, rms_after = before.pow(2).mean().sqrt(), after.pow(2).mean().sqrt()
    assert float(rms_after) <= 0.2 * float(rms_before), (rms_before, rms_after)
    rot_before = tf.so3_log(twin.loaded_pose(q, w)[:, :3, :3] @ target[:, :3, :3].transpose(-1, -2)).norm(dim=-1)
    rot_after = tf.so3_log(loaded[:, :3, :3] @ target[:, :3, :3].transpose(-1, -2)).norm(dim=-1)
    assert float(rot_after.pow(2).mean().sqrt()) <= 0.2 * float(rot_before.pow(2).mean().sqrt())


def test_with_the_true_springs_the_iteration_hits_the_target(rig):
    twin, _, test = rig
    q, w = test.q[:20], test.wrench[:20]
    target = twin.unloaded_pose(q)
    result = compensate_deflection(twin.model, twin.x_true, twin.compliance, target, w, q,
                                   position_tol_m=1e-9, rotation_tol_rad=1e-9)
    assert bool(result.converged.all()) and result.iterations <= 6
    loaded = twin.loaded_pose(result.q, w)
    assert float((loaded[:, :3, 3] - target[:, :3, 3]).norm(dim=-1).max()) < 1e-8
    # The offset target sits opposite to the deflection.
    bent = twin.loaded_pose(q, w)[:, :3, 3] - target[:, :3, 3]
    shift = result.target_offset[:, :3, 3] - target[:, :3, 3]
    torch.testing.assert_close(shift, -bent, atol=5e-6, rtol=0)


def test_position_only_and_batched(rig, estimate):
    _twin, _, test = rig
    q = test.q[:6].reshape(2, 3, -1)
    w = test.wrench[:6].reshape(2, 3, 6)
    comp = DeflectionCompensator(estimate.model, estimate.x, estimate.compliance, position_only=True)
    result = comp(q, w)
    assert result.q.shape == (2, 3, 6) and result.position_error.shape == (2, 3)
    assert float(result.position_error.max()) < 1e-7
    flat = comp(q.reshape(6, -1), w.reshape(6, 6))
    torch.testing.assert_close(result.q.reshape(6, -1), flat.q, atol=1e-9, rtol=0)
