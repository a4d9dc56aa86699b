"""The profile-sensor measurement model: laser-plane points, flange poses, target planes.

Frames: ``sensor`` has x along the laser line (``u``), z along the depth (``w``) and y normal
to the laser plane, so a profile point is ``p_sensor = (u, 0, w)``. The unknown extrinsics are
``T_flange_sensor = (R, t)``: ``p_flange = R p_sensor + t = u r1 + w r3 + t`` with ``r1, r3``
the first and third columns of ``R``. A placement of the plane target is ``n . x = c`` in the
robot ``base`` frame (``|n| = 1``, ``c`` in m). Everything is SI (m, rad) and float64.
"""

from __future__ import annotations

import math

import torch

from torchcal.kinematics import transforms as tf


def sensor_points(uw: torch.Tensor) -> torch.Tensor:
    """``(K, 3)`` points ``(u, 0, w)`` in the ``sensor`` frame from ``(K, 2)`` ``(u, w)``, m."""
    zero = torch.zeros_like(uw[:, :1])
    return torch.cat([uw[:, :1], zero, uw[:, 1:]], -1)


def base_points(
    T_base_flange: torch.Tensor, point_scan: torch.Tensor, uw: torch.Tensor, R: torch.Tensor, t: torch.Tensor
) -> torch.Tensor:
    """Profile points in the robot ``base`` frame ``(K, 3)``, m.

    Args:
        T_base_flange: ``(S, 4, 4)`` flange pose of each scan.
        point_scan: ``(K,)`` scan index of each point.
        uw: ``(K, 2)`` points in the laser plane, m.
        R, t: ``R_flange_sensor`` ``(3, 3)`` and ``t_flange_sensor`` ``(3,)``, m.
    """
    p_flange = sensor_points(uw) @ R.T + t
    pose = T_base_flange[point_scan]
    return (pose[:, :3, :3] @ p_flange.unsqueeze(-1)).squeeze(-1) + pose[:, :3, 3]


def plane_distances(points: torch.Tensor, point_plane: torch.Tensor, normals: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Signed point-to-plane distances ``n . p - c`` ``(K,)``, m."""
    return (points * normals[point_plane]).sum(-1) - offsets[point_plane]


def fit_plane(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Total-least-squares plane of ``(K, 3)`` points: unit normal, offset ``c`` and singular values.

    The normal is the right singular vector of the centred points with the smallest singular
    value (the exact minimizer of the summed squared distances); the returned singular values
    ``(3,)`` tell whether the points span a plane (the second one is ~0 for collinear points).
    """
    centre = points.mean(0)
    _, s, vh = torch.linalg.svd(points - centre, full_matrices=False)
    normal = vh[-1]
    return normal, normal @ centre, s


def fit_planes(points: torch.Tensor, point_plane: torch.Tensor, n_planes: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`fit_plane` per placement: normals ``(P, 3)``, offsets ``(P,)``, singular values ``(P, 3)``."""
    normals, offsets, spreads = [], [], []
    for k in range(n_planes):  # a handful of placements, not a hot loop
        n, c, s = fit_plane(points[point_plane == k])
        normals.append(n)
        offsets.append(c)
        spreads.append(s)
    return torch.stack(normals), torch.stack(offsets), torch.stack(spreads)


def unit_columns(r1: torch.Tensor, r3: torch.Tensor) -> torch.Tensor:
    """The patent's normalization: ``r1, r3`` scaled to unit length, ``r2 = r3 x r1`` normalized.

    Unit-norm columns but not exactly orthogonal when ``r1 . r3 != 0`` (their angle error is kept,
    as least squares left it); :func:`~torchcal.kinematics.transforms.project_to_so3` gives the orthonormal matrix.
    """
    a = r1 / r1.norm()
    c = r3 / r3.norm()
    b = torch.linalg.cross(c, a)
    return torch.stack([a, b / b.norm(), c], -1)


def rotation_from_columns(r1: torch.Tensor, r3: torch.Tensor) -> torch.Tensor:
    """``[r1, r3 x r1, r3]`` projected onto SO(3) by :func:`~torchcal.kinematics.transforms.project_to_so3`."""
    return tf.project_to_so3(torch.stack([r1, torch.linalg.cross(r3, r1), r3], -1))


def rotation_angle_deg(R_a: torch.Tensor, R_b: torch.Tensor) -> float:
    """Angle of ``R_a^T R_b`` in degrees."""
    return math.degrees(float(tf.rotation_angle(R_a.T @ R_b)))


def orthogonal_basis(normal: torch.Tensor) -> torch.Tensor:
    """Two unit vectors ``(2, 3)`` orthogonal to ``normal`` and to each other."""
    helper = torch.zeros(3, dtype=normal.dtype, device=normal.device)
    helper[int(normal.abs().argmin())] = 1.0
    b1 = torch.linalg.cross(normal, helper)
    b1 = b1 / b1.norm()
    return torch.stack([b1, torch.linalg.cross(normal, b1)])
