"""Helpers on transforms: broadcasting as torch does it, without torch's first-call imports."""

from __future__ import annotations

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
