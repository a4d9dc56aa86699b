"""Geometric Jacobian of the TCP with respect to the joint angles.

Rows ``[v; w]``: linear velocity of the TCP point and angular velocity of the tool, both in the
``instrument`` frame (the ``base`` frame when the model's instrument frame is the identity), per
rad/s of each joint. Columns follow the joint order.
"""

from __future__ import annotations

import torch

from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.mdh import chain_transforms


def joint_frames(model: ErrorModel, q: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Axes ``z_i`` ``(..., N, 3)`` and origins ``o_i`` ``(..., N, 3)`` of every joint, instrument frame."""
    rot, pos = chain_transforms(q, model.table(x), all_frames=True)
    world = model.instrument_from_base(x) @ model.T_base_0.to(q)
    r_w, p_w = world[..., :3, :3].unsqueeze(-3), world[..., :3, 3].unsqueeze(-2)
    axes = (r_w @ rot[..., :, 2:3]).squeeze(-1)
    origins = (r_w @ pos.unsqueeze(-1)).squeeze(-1) + p_w
    return axes, origins


def geometric_jacobian(model: ErrorModel, q: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """TCP pose ``T_instrument_tool`` ``(..., 4, 4)`` and geometric Jacobian ``(..., 6, N)``."""
    pose = model.tcp_pose(q, x)
    axes, origins = joint_frames(model, q, x)
    return pose, jacobian_columns(axes, origins, pose[..., :3, 3])


def jacobian_columns(axes: torch.Tensor, origins: torch.Tensor, point: torch.Tensor) -> torch.Tensor:
    """Geometric Jacobian ``(..., 6, N)`` of ``point`` ``(..., 3)`` from revolute joint axes and origins ``(..., N, 3)``.

    Column ``i`` is ``[z_i x (p - o_i); z_i]``, in the frame the axes, origins and point are given in.
    """
    lever = point[..., None, :] - origins
    linear = torch.linalg.cross(axes, lever, dim=-1)
    return torch.cat([linear, axes], -1).transpose(-1, -2)
