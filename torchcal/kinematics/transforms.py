"""Batched rigid-body helpers on homogeneous transforms ``(..., 4, 4)``.

Angles in rad, lengths in whatever unit the caller uses (SI inside torchcal).
"""

from __future__ import annotations

import numpy as np
import torch


def broadcast_shapes(*shapes: tuple[int, ...]) -> torch.Size:
    """The shape ``shapes`` broadcast to, as :func:`torch.broadcast_shapes` gives it.

    numpy's rule is the same; torch's first call imports its symbolic-shape machinery (sympy),
    0.6 s once in every process that computes a transform.
    """
    return torch.Size(np.broadcast_shapes(*shapes))


def homogeneous(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """Stack a rotation ``(..., 3, 3)`` and translation ``(..., 3)`` into ``(..., 4, 4)``."""
    batch = broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    out = torch.zeros(*batch, 4, 4, dtype=rotation.dtype, device=rotation.device)
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def invert(transform: torch.Tensor) -> torch.Tensor:
    """Inverse of a rigid transform ``(..., 4, 4)``."""
    rot_t = transform[..., :3, :3].transpose(-1, -2)
    return homogeneous(rot_t, -(rot_t @ transform[..., :3, 3:4]).squeeze(-1))


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix of ``(..., 3)`` vectors."""
    zero = torch.zeros_like(v[..., 0])
    x, y, z = v.unbind(-1)
    return torch.stack(
        [
            torch.stack([zero, -z, y], -1),
            torch.stack([z, zero, -x], -1),
            torch.stack([-y, x, zero], -1),
        ],
        -2,
    )


def so3_exp(rotvec: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a rotation vector ``(..., 3)`` (axis times angle, rad).

    Uses the Taylor form near zero so that gradients stay finite at the identity,
    which is where calibration corrections start.
    """
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True).unsqueeze(-1)
    small = theta2 < 1e-12
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    k = skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def so3_log(rotation: torch.Tensor) -> torch.Tensor:
    """Rotation vector ``(..., 3)`` of a rotation matrix (angles below pi)."""
    cos = ((rotation.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    theta = torch.acos(cos)
    vee = torch.stack(
        [
            rotation[..., 2, 1] - rotation[..., 1, 2],
            rotation[..., 0, 2] - rotation[..., 2, 0],
            rotation[..., 1, 0] - rotation[..., 0, 1],
        ],
        -1,
    )
    sin = torch.sin(theta)
    scale = torch.where(theta < 1e-6, 0.5 + theta**2 / 12.0, theta / (2.0 * sin.clamp_min(1e-300)))
    return vee * scale.unsqueeze(-1)


def rot_x(angle: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    return torch.stack(
        [torch.stack([one, zero, zero], -1), torch.stack([zero, c, -s], -1), torch.stack([zero, s, c], -1)],
        -2,
    )


def rot_y(angle: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    return torch.stack(
        [torch.stack([c, zero, s], -1), torch.stack([zero, one, zero], -1), torch.stack([-s, zero, c], -1)],
        -2,
    )


def rot_z(angle: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    return torch.stack(
        [torch.stack([c, -s, zero], -1), torch.stack([s, c, zero], -1), torch.stack([zero, zero, one], -1)],
        -2,
    )


def euler_xyz_to_matrix(angles: torch.Tensor) -> torch.Tensor:
    """Fixed-axis XYZ angles ``(rx, ry, rz)`` (rad) to ``R = Rz(rz) Ry(ry) Rx(rx)``.

    This is the convention of the measurement contract's ``rx, ry, rz`` columns and of URDF ``rpy``.
    """
    rx, ry, rz = angles.unbind(-1)
    return rot_z(rz) @ rot_y(ry) @ rot_x(rx)


def matrix_to_euler_xyz(rotation: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`euler_xyz_to_matrix` (``ry`` in ``[-pi/2, pi/2]``)."""
    ry = torch.asin((-rotation[..., 2, 0]).clamp(-1.0, 1.0))
    rx = torch.atan2(rotation[..., 2, 1], rotation[..., 2, 2])
    rz = torch.atan2(rotation[..., 1, 0], rotation[..., 0, 0])
    return torch.stack([rx, ry, rz], -1)


def rigid_registration(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Closed-form least-squares rigid transform ``T`` with ``target ~ T @ source`` (Kabsch/Umeyama).

    Args:
        source: ``(n, 3)`` points in the frame being registered (e.g. robot ``base``).
        target: ``(n, 3)`` the same points measured in the reference frame (e.g. ``tracker``).

    Returns:
        ``(4, 4)`` transform ``T_target_source`` without scaling.
    """
    mu_s, mu_t = source.mean(0), target.mean(0)
    rotation = project_to_so3((target - mu_t).T @ (source - mu_s))
    return homogeneous(rotation, mu_t - rotation @ mu_s)


def project_to_so3(matrix: torch.Tensor) -> torch.Tensor:
    """The rotation ``(..., 3, 3)`` nearest to ``matrix`` in the Frobenius norm (SVD polar factor, det +1).

    Of a sum ``sum_i A_i^T B_i`` it is the rotation ``X`` that best fits ``B_i ~ A_i X`` (the chordal
    mean, Kabsch's solution).
    """
    u, _, vh = torch.linalg.svd(matrix)
    d = torch.sign(torch.linalg.det(u @ vh))
    fix = torch.ones(*d.shape, 3, dtype=matrix.dtype, device=matrix.device)
    fix[..., -1] = d
    return (u * fix.unsqueeze(-2)) @ vh


def rotation_angle(rotation: torch.Tensor) -> torch.Tensor:
    """Angle ``(...)`` (rad, in ``[0, pi]``) of rotation matrices ``(..., 3, 3)``: the geodesic distance to the identity.

    From the skew part and the trace together (``atan2``): ``acos`` of the trace alone loses half the
    digits of a small angle (1e-8 rad reads as 0 or 1.5e-8).
    """
    vee = torch.stack([rotation[..., 2, 1] - rotation[..., 1, 2], rotation[..., 0, 2] - rotation[..., 2, 0],
                       rotation[..., 1, 0] - rotation[..., 0, 1]], -1)
    trace = rotation.diagonal(dim1=-2, dim2=-1).sum(-1)
    return torch.atan2(vee.norm(dim=-1), trace - 1.0)
