"""Virtual joint method (VJM): TCP deflection of a serial robot with 6-D springs in its joints.

Every joint ``i`` carries a virtual spring placed at its MDH frame ``i`` (after the joint
rotation). The spring's deformation ``theta_i = [t; r]`` (3 translations in m, 3 rotations in
rad) is a twist expressed in that joint frame; its compliance ``C_i = K_i^-1`` is a symmetric
``6 x 6`` matrix in the same coordinates (m/N, rad/(N m) on the diagonal; diagonal by default).
The classic model keeps only ``C_i[5, 5]``: rotation about the joint's own axis.

For a wrench ``W = [f; m]`` acting at the TCP (force in N, moment about the TCP in N m, both in
the ``instrument`` frame) the springs deform by ``theta = C J_theta^T W`` and the TCP moves, to
first order, by::

    dX = J_theta C J_theta^T W,    J_theta = [J_1 ... J_N] (6 x 6N)

where ``J_i`` maps a twist in joint frame ``i`` to ``[TCP linear velocity; angular velocity]`` in
the ``instrument`` frame: ``J_i = [[R_i, -[p - o_i]x R_i], [0, R_i]]`` with ``R_i, o_i`` the
joint frame's orientation and origin and ``p`` the TCP.

Everything is batched over leading dimensions of ``q``.
"""

from __future__ import annotations

from typing import Literal

import torch

from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.mdh import chain_transforms

SPRING_COMPONENTS = ("tx", "ty", "tz", "rx", "ry", "rz")
"""Order of the 6 virtual-joint coordinates: translations then rotations, joint frame axes."""

WrenchFrame = Literal["tool", "instrument"]


def spring_names(n_joints: int) -> tuple[str, ...]:
    """Names ``k_j{i}_{tx..rz}`` of the ``6 N`` diagonal stiffness entries, joint-major order."""
    return tuple(f"k_j{i}_{c}" for i in range(1, n_joints + 1) for c in SPRING_COMPONENTS)


def compliance_from_stiffness(stiffness: torch.Tensor) -> torch.Tensor:
    """Diagonal compliance ``(..., N, 6, 6)`` from diagonal stiffness ``(..., N, 6)``.

    Units: N/m for translations, N m/rad for rotations. ``inf`` means rigid (zero compliance).
    """
    return torch.diag_embed(1.0 / stiffness.to(torch.float64))


def classic_compliance(
    joint_stiffness: torch.Tensor, device: str | torch.device | None = None
) -> torch.Tensor:
    """Compliance ``(N, 6, 6)`` of the classic model: one rotational spring per joint axis.

    Args:
        joint_stiffness: ``(N,)`` stiffness about each joint axis, N m/rad.
        device: where the result lives (default: that of ``joint_stiffness``).
    """
    k = joint_stiffness.to(device=device or joint_stiffness.device, dtype=torch.float64)
    stiffness = torch.full((*k.shape, 6), torch.inf, dtype=torch.float64, device=k.device)
    stiffness[..., 5] = k
    return compliance_from_stiffness(stiffness)


def joint_poses(model: ErrorModel, q: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Poses ``T_instrument_joint_i`` ``(..., N, 4, 4)`` of every MDH joint frame (after rotation)."""
    rot, pos = chain_transforms(q, model.table(x), all_frames=True)
    world = model.instrument_from_base(x) @ model.T_base_0.to(q)
    return world.unsqueeze(-3) @ tf.homogeneous(rot, pos)


def twist_blocks(frames: torch.Tensor, tcp: torch.Tensor) -> torch.Tensor:
    """Per-joint blocks ``J_i`` ``(..., N, 6, 6)`` for joint frames ``(..., N, 4, 4)`` and TCP ``(..., 3)``.

    Block ``i`` maps a twist ``[t; r]`` in joint frame ``i`` to the TCP's ``[dp; dphi]`` in the
    frame ``frames`` are expressed in.
    """
    rot, origin = frames[..., :3, :3], frames[..., :3, 3]
    lever = tcp.unsqueeze(-2) - origin
    upper = torch.cat([rot, -tf.skew(lever) @ rot], -1)
    lower = torch.cat([torch.zeros_like(rot), rot], -1)
    return torch.cat([upper, lower], -2)


def virtual_joint_jacobian(
    model: ErrorModel, q: torch.Tensor, x: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """TCP pose ``T_instrument_tool`` ``(..., 4, 4)`` and ``J_theta`` ``(..., 6, 6N)``.

    Columns are joint-major in :data:`SPRING_COMPONENTS` order (see :func:`spring_names`); rows
    ``[dp (m); dphi (rad)]`` in the ``instrument`` frame.
    """
    pose = model.tcp_pose(q, x)
    blocks = twist_blocks(joint_poses(model, q, x), pose[..., :3, 3])
    return pose, _blocks_to_matrix(blocks)


def _blocks_to_matrix(blocks: torch.Tensor) -> torch.Tensor:
    n = blocks.shape[-3]
    return blocks.transpose(-3, -2).reshape(*blocks.shape[:-3], 6, 6 * n)


def wrench_in_instrument(
    wrench: torch.Tensor, tcp_pose: torch.Tensor, wrench_frame: WrenchFrame = "tool"
) -> torch.Tensor:
    """``[f; m]`` ``(..., 6)`` at the TCP in the ``instrument`` frame.

    Args:
        wrench: ``(..., 6)`` force (N) and moment about the TCP (N m).
        tcp_pose: ``(..., 4, 4)`` ``T_instrument_tool``.
        wrench_frame: ``"tool"`` when the components are along the tool axes (as an F/T sensor
            reports them), ``"instrument"`` when already in the instrument frame.
    """
    if wrench_frame == "instrument":
        return wrench
    if wrench_frame != "tool":
        raise ValueError(f"wrench_frame must be 'tool' or 'instrument', got {wrench_frame!r}")
    rot = tcp_pose[..., :3, :3]
    f = (rot @ wrench[..., :3].unsqueeze(-1)).squeeze(-1)
    m = (rot @ wrench[..., 3:].unsqueeze(-1)).squeeze(-1)
    return torch.cat([f, m], -1)


def spring_deformations(
    blocks: torch.Tensor, compliance: torch.Tensor, wrench_instrument: torch.Tensor
) -> torch.Tensor:
    """Virtual-joint deformations ``theta_i = C_i J_i^T W`` ``(..., N, 6)`` (m, rad, joint frames)."""
    torque = (blocks.transpose(-1, -2) @ wrench_instrument.unsqueeze(-2).unsqueeze(-1)).squeeze(-1)
    return (compliance @ torque.unsqueeze(-1)).squeeze(-1)


def joint_deformations(
    model: ErrorModel,
    q: torch.Tensor,
    x: torch.Tensor,
    compliance: torch.Tensor,
    wrench: torch.Tensor,
    *,
    wrench_frame: WrenchFrame = "tool",
) -> torch.Tensor:
    """Spring deformations ``(..., N, 6)`` of the unloaded configuration under ``wrench``.

    Args:
        compliance: ``(N, 6, 6)`` (or batched ``(..., N, 6, 6)``) joint-frame compliance.
        wrench: ``(..., 6)`` N, N m at the TCP.
    """
    pose = model.tcp_pose(q, x)
    blocks = twist_blocks(joint_poses(model, q, x), pose[..., :3, 3])
    return spring_deformations(blocks, compliance.to(q), wrench_in_instrument(wrench, pose, wrench_frame))


def deflection(
    model: ErrorModel,
    q: torch.Tensor,
    x: torch.Tensor,
    compliance: torch.Tensor,
    wrench: torch.Tensor,
    *,
    wrench_frame: WrenchFrame = "tool",
) -> torch.Tensor:
    """First-order TCP deflection ``dX = J_theta C J_theta^T W`` ``(..., 6)``.

    Returns ``[dp (m); dphi (rad, rotation vector)]`` in the ``instrument`` frame.
    """
    pose = model.tcp_pose(q, x)
    blocks = twist_blocks(joint_poses(model, q, x), pose[..., :3, 3])
    theta = spring_deformations(blocks, compliance.to(q), wrench_in_instrument(wrench, pose, wrench_frame))
    return (blocks @ theta.unsqueeze(-1)).squeeze(-1).sum(-2)


def cartesian_compliance(
    model: ErrorModel, q: torch.Tensor, x: torch.Tensor, compliance: torch.Tensor
) -> torch.Tensor:
    """TCP compliance matrix ``J_theta C J_theta^T`` ``(..., 6, 6)`` in the ``instrument`` frame."""
    pose = model.tcp_pose(q, x)
    blocks = twist_blocks(joint_poses(model, q, x), pose[..., :3, 3])
    return (blocks @ compliance.to(q) @ blocks.transpose(-1, -2)).sum(-3)
