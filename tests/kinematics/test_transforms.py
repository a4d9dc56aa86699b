"""Helpers on transforms against closed-form truth; broadcasting as torch does it, without torch's first-call imports."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import pytest
import torch

from torchcal.kinematics import transforms as tf


@pytest.mark.parametrize("shapes", [((), ()), ((3,), ()), ((1, 4), (5, 1)), ((2, 1, 3), (4, 1), ()), ((0, 1), (1, 6))])
def test_broadcast_shapes_is_torchs(shapes):
    assert tf.broadcast_shapes(*shapes) == torch.broadcast_shapes(*shapes)
    assert isinstance(tf.broadcast_shapes(*shapes), torch.Size)


def test_broadcast_shapes_refuses_what_torch_refuses():
    with pytest.raises(RuntimeError):
        torch.broadcast_shapes((2, 3), (4, 3))
    with pytest.raises(ValueError, match="broadcast"):
        tf.broadcast_shapes((2, 3), (4, 3))


def test_forward_kinematics_does_not_import_sympy():
    """torch.broadcast_shapes imports sympy (0.6 s) on its first call; the kinematics use tf.broadcast_shapes."""
    code = textwrap.dedent("""
        import sys
        import torch
        from torchcal.kinematics.mdh import chain_transforms
        from torchcal.kinematics.robot import default_robot_path, load_robot
        robot = load_robot(default_robot_path())
        q = torch.zeros(3, robot.dof, dtype=torch.float64)
        chain_transforms(q, robot.table)
        print("sympy" in sys.modules)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def _random_rotation(gen, *batch):
    return tf.so3_exp(torch.randn(*batch, 3, generator=gen, dtype=torch.float64))


def test_polar_projection_removes_a_symmetric_stretch(generator):
    R = _random_rotation(generator)
    S = torch.randn(3, 3, generator=generator, dtype=torch.float64) * 0.01
    S = 0.5 * (S + S.T)
    # R (I + S) with S symmetric: its polar factor is R itself
    torch.testing.assert_close(tf.project_to_so3(R @ (torch.eye(3, dtype=torch.float64) + S)), R, rtol=0, atol=1e-12)
    reflected = R @ torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    assert math.isclose(float(torch.det(tf.project_to_so3(reflected))), 1.0, abs_tol=1e-12)


def test_polar_projection_of_a_batch_is_each_ones(generator):
    stretched = _random_rotation(generator, 4) @ (torch.eye(3, dtype=torch.float64) + 0.01 * torch.randn(4, 3, 3, generator=generator, dtype=torch.float64))
    stretched[2] = -stretched[2]  # det < 0: the nearest rotation, not a reflection
    batch = tf.project_to_so3(stretched)
    torch.testing.assert_close(batch, torch.stack([tf.project_to_so3(m) for m in stretched]), rtol=0, atol=1e-14)
    torch.testing.assert_close(torch.linalg.det(batch), torch.ones(4, dtype=torch.float64))


def test_rotation_angle_is_the_rotation_vectors_norm_down_to_tiny_angles(generator):
    axes = torch.nn.functional.normalize(torch.randn(6, 3, generator=generator, dtype=torch.float64), dim=-1)
    angles = torch.tensor([1e-9, 1e-6, 0.01, 1.0, 3.0, math.pi - 1e-6], dtype=torch.float64)
    rotations = tf.so3_exp(axes * angles.unsqueeze(-1))
    torch.testing.assert_close(tf.rotation_angle(rotations), angles, rtol=1e-9, atol=1e-15)
    # the angle between two rotations, either way round
    a, b = _random_rotation(generator), _random_rotation(generator)
    torch.testing.assert_close(tf.rotation_angle(a.T @ b), tf.rotation_angle(b.T @ a), rtol=0, atol=1e-14)
