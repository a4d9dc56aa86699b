"""Profile-sensor geometry helpers against closed-form truth."""

from __future__ import annotations

import math

import torch

from torchcal.instruments.profile.model import (
    base_points,
    fit_plane,
    orthogonal_basis,
    rotation_from_columns,
    sensor_points,
    unit_columns,
)
from torchcal.kinematics import transforms as tf


def _random_rotation(gen):
    return tf.so3_exp(torch.randn(3, generator=gen, dtype=torch.float64))


def test_unit_columns_and_rotation_from_columns(generator):
    R = _random_rotation(generator)
    r1, r3 = 1.02 * R[:, 0], 0.97 * R[:, 2] + 0.001 * R[:, 1]
    U = unit_columns(r1, r3)
    torch.testing.assert_close(U.norm(dim=0), torch.ones(3, dtype=torch.float64))
    torch.testing.assert_close(U[:, 1], torch.linalg.cross(U[:, 2], U[:, 0]) / torch.linalg.cross(U[:, 2], U[:, 0]).norm())
    torch.testing.assert_close(rotation_from_columns(2.0 * R[:, 0], 0.5 * R[:, 2]), R, rtol=0, atol=1e-12)
    assert float(rotation_from_columns(r1, r3).T.__matmul__(R).diagonal().sum()) > 2.999


def test_base_points_compose_flange_and_sensor_frames(generator):
    T_bf = tf.homogeneous(_random_rotation(generator), torch.randn(2, 3, generator=generator, dtype=torch.float64))
    R, t = _random_rotation(generator), torch.tensor([0.01, -0.02, 0.1], dtype=torch.float64)
    uw = torch.tensor([[0.01, 0.1], [-0.02, 0.12], [0.0, 0.09]], dtype=torch.float64)
    scan = torch.tensor([0, 1, 1])
    got = base_points(T_bf, scan, uw, R, t)
    T_bs = T_bf @ tf.homogeneous(R, t)
    ref = torch.stack([T_bs[s, :3, :3] @ p + T_bs[s, :3, 3] for s, p in zip(scan.tolist(), sensor_points(uw))])
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-15)


def test_fit_plane_recovers_a_plane_and_flags_collinear_points(generator):
    n = torch.tensor([0.3, -0.4, 0.866], dtype=torch.float64)
    n = n / n.norm()
    b = orthogonal_basis(n)
    assert float((b @ n).abs().max()) < 1e-15 and abs(float(b[0] @ b[1])) < 1e-15
    coeff = torch.randn(50, 2, generator=generator, dtype=torch.float64)
    points = coeff @ b + 0.7 * n
    normal, c, _s = fit_plane(points)
    assert abs(abs(float(normal @ n)) - 1) < 1e-14 and math.isclose(abs(float(c)), 0.7, rel_tol=1e-12)
    line = torch.linspace(0, 1, 20, dtype=torch.float64).unsqueeze(-1) * b[0] + 0.7 * n
    assert float(fit_plane(line)[2][1]) < 1e-12
