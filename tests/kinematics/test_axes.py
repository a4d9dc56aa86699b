"""Axis method: MDH(+beta) parameters re-derived from joint axes recover known parameters."""

from __future__ import annotations

import math

import torch

from torchcal.kinematics import transforms as tf
from torchcal.kinematics.axes import mdh_from_axes
from torchcal.kinematics.mdh import chain_transforms


def _axes_of(table: torch.Tensor):
    zero = torch.zeros(table.shape[0], dtype=torch.float64)
    rot, pos = chain_transforms(zero, table, all_frames=True)
    flange = tf.homogeneous(rot[-1], pos[-1])
    return pos, rot[..., :, 2], flange


def test_recovers_dh_like_table_exactly(robot):
    table = robot.table.clone()
    table[:, 3] = 0.0  # zero offsets are a gauge choice of the method (x_i along the common normal)
    table[1, 3] = 0.0
    points, dirs, flange = _axes_of(table)
    derived = mdh_from_axes(points, dirs, flange)
    rot, pos = chain_transforms(torch.zeros(6, dtype=torch.float64), derived.table)
    rebuilt = derived.T_base_0 @ tf.homogeneous(rot, pos) @ derived.T_n_flange
    assert (rebuilt - flange).abs().max() < 1e-12
    # same axes: alpha, a, beta of every row agree with the known table
    assert torch.allclose(derived.table[1:, :3], table[1:, :3], atol=1e-9)


def test_recovers_beta_on_nearly_parallel_axes():
    deg = math.pi / 180
    # rows [alpha, a, beta, theta, d]; axes 2 and 3 nearly parallel, tilted by beta = 0.05 deg
    table = torch.tensor(
        [
            [0.0, 0.0, 0.0, 0.0, 0.4],
            [-90 * deg, 0.025, 0.0, 0.0, 0.0],
            [0.01 * deg, 0.455, 0.05 * deg, 0.0, 0.0],
            [-90 * deg, 0.035, 0.0, 0.0, 0.42],
        ],
        dtype=torch.float64,
    )
    points, dirs, flange = _axes_of(table)
    derived = mdh_from_axes(points, dirs, flange)
    assert abs(float(derived.table[2, 2]) - 0.05 * deg) < 1e-9
    assert abs(float(derived.table[2, 0]) - 0.01 * deg) < 1e-9
    assert abs(float(derived.table[2, 1]) - 0.455) < 1e-9
    assert abs(float(derived.table[2, 4])) < 1e-9
    rot, pos = chain_transforms(torch.zeros(4, dtype=torch.float64), derived.table)
    rebuilt = derived.T_base_0 @ tf.homogeneous(rot, pos) @ derived.T_n_flange
    assert (rebuilt - flange).abs().max() < 1e-12
