"""Batched numerical inverse kinematics by damped least squares (Levenberg-Marquardt in q).

Used by compensation, where the solution is always near the starting joint vector (the nominal
command), so a local Newton method converges in a few iterations. No Python loop over poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.joint_jacobian import geometric_jacobian


@dataclass(frozen=True)
class IKResult:
    """Joint solution ``q (..., N)`` rad, final position error (m), rotation error (rad), iterations."""

    q: torch.Tensor
    position_error: torch.Tensor
    rotation_error: torch.Tensor
    iterations: int
    converged: torch.Tensor


def pose_error(target: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
    """``[p_t - p, log(R_t R^T)]`` ``(..., 6)`` in the frame both poses are expressed in."""
    dp = target[..., :3, 3] - current[..., :3, 3]
    dr = tf.so3_log(target[..., :3, :3] @ current[..., :3, :3].transpose(-1, -2))
    return torch.cat([dp, dr], -1)


def solve_ik(
    model: ErrorModel,
    x: torch.Tensor,
    target: torch.Tensor,
    q0: torch.Tensor,
    *,
    position_only: bool = False,
    max_iterations: int = 50,
    position_tol_m: float = 1e-10,
    rotation_tol_rad: float = 1e-10,
    damping: float = 1e-6,
) -> IKResult:
    """Joints that put the TCP of ``model`` (parameters ``x``) at ``target``.

    Args:
        target: ``(..., 4, 4)`` TCP pose, or ``(..., 3)`` TCP position when ``position_only``,
            instrument frame, m.
        q0: ``(..., N)`` starting joints, rad.
        damping: Tikhonov damping ``lambda`` of ``J^T (J J^T + lambda^2 I)^-1``; kept tiny because
            compensation targets are regular poses (singular paths use the motion module).
    """
    q = q0.clone()
    rows = 3 if position_only else 6
    eye = torch.eye(rows, dtype=q.dtype, device=q.device)
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 (read after the loop)
        pose, jac = geometric_jacobian(model, q, x)
        if position_only:
            err = target - pose[..., :3, 3]
            jac = jac[..., :3, :]
        else:
            err = pose_error(target, pose)
        perr = err[..., :3].norm(dim=-1)
        rerr = err[..., 3:].norm(dim=-1) if not position_only else torch.zeros_like(perr)
        done = (perr < position_tol_m) & (rerr < rotation_tol_rad)
        if bool(done.all()):
            break
        jjt = jac @ jac.transpose(-1, -2) + damping**2 * eye
        step = jac.transpose(-1, -2) @ torch.linalg.solve(jjt, err.unsqueeze(-1))
        q = q + step.squeeze(-1) * (~done).unsqueeze(-1)
    pose = model.tcp_pose(q, x)
    if position_only:
        perr = (target - pose[..., :3, 3]).norm(dim=-1)
        rerr = torch.zeros_like(perr)
    else:
        err = pose_error(target, pose)
        perr, rerr = err[..., :3].norm(dim=-1), err[..., 3:].norm(dim=-1)
    converged = (perr < max(position_tol_m, 1e-9)) & (rerr < max(rotation_tol_rad, 1e-9))
    return IKResult(q=q, position_error=perr, rotation_error=rerr, iterations=iterations, converged=converged)
