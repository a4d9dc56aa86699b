"""The stiffness stage of the exported graphs: first-order VJM deflection as a fixed tensor graph.

Inputs are what :class:`~torchcal.compensate.chain.ChainGraph` gives the compensator anyway: the
calibrated TCP pose ``T_base_tool`` and the joint frames ``T_base_i`` (after joint rotation,
where the virtual springs of :mod:`torchcal.stiffness.vjm` sit), plus the expected wrench. With
``l_i = p - o_i`` (TCP minus origin of joint frame ``i``) and the wrench ``[f; m]`` in ``base``,
the spring of joint ``i`` deforms by ``theta_i = C_i [R_i^T f; R_i^T (l_i x f + m)]`` (its own
frame) and moves the TCP by ``dp_i = R_i t_i + (R_i r_i) x l_i``, ``dphi_i = R_i r_i``; the sums
over joints are the deflection ``J C J^T W`` of :func:`torchcal.stiffness.vjm.deflection` (equal
to rounding, tested). Cross products are :func:`torchcal.compensate.linalg.cross` (index
permutations: ONNX has no cross operator).

The loaded TCP orientation is ``exp([dphi]x) R`` with the exponential to second order,
``I + K + K^2 / 2``: elastic rotations are below ~1e-2 rad, where the third-order term
(< 2e-7 rad) is below the first-order VJM law's own truncation (~|dphi|^2).
"""

from __future__ import annotations

import torch
from torch import nn

from torchcal.compensate.linalg import cross

WRENCH_FRAMES = ("tool", "base")


def skew(w: torch.Tensor) -> torch.Tensor:
    """``[w]x`` ``(..., 3, 3)`` of ``w`` ``(..., 3)``."""
    x, y, z = w.unbind(-1)
    zero = torch.zeros_like(x)
    rows = [zero, -z, y, z, zero, -x, -y, x, zero]
    return torch.stack(rows, -1).reshape(*w.shape[:-1], 3, 3)


class DeflectionGraph(nn.Module):
    """``(pose, joint frames, wrench) -> (dp, dphi)``: TCP deflection in ``base`` (m, rad).

    Args:
        compliance: ``(N, 6, 6)`` joint-frame compliance, SI (zero rows: rigid).
        wrench_frame: ``"tool"`` (the wrench's components along the tool axes, as an F/T
            sensor at the TCP reports them) or ``"base"`` (along the robot base axes).
        dtype / device: of the constant.
    """

    # buffers, registered in __init__ (declared so that type checkers see tensors, not Tensor | Module)
    compliance_t: torch.Tensor

    def __init__(
        self,
        compliance: torch.Tensor,
        *,
        wrench_frame: str = "tool",
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__()
        if wrench_frame not in WRENCH_FRAMES:
            raise ValueError(f"wrench_frame must be one of {WRENCH_FRAMES}, got {wrench_frame!r}")
        self.wrench_frame = wrench_frame
        # row vectors below: theta^T = tau^T C^T
        self.register_buffer("compliance_t", compliance.to(torch.float64).transpose(-1, -2).contiguous().to(device, dtype))

    def forward(self, pose: torch.Tensor, frames: torch.Tensor, wrench: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Deflection of the TCP under ``wrench``.

        Args:
            pose: ``(B, 4, 4)`` unloaded ``T_base_tool``.
            frames: ``(B, N, 4, 4)`` joint frames ``T_base_i``.
            wrench: ``(B, 6)`` ``[f (N); m (N m)]``, force at the TCP and moment about it.

        Returns:
            ``dp (B, 3)`` m and ``dphi (B, 3)`` rad (rotation vector), ``base`` frame.
        """
        f = wrench[:, None, 0:3]  # (B, 1, 3) row vectors
        m = wrench[:, None, 3:6]
        if self.wrench_frame == "tool":  # structural, fixed at construction
            rot_t = pose[:, :3, :3].transpose(-1, -2)
            f, m = f @ rot_t, m @ rot_t  # (R f)^T = f^T R^T
        rot = frames[..., :3, :3]  # (B, N, 3, 3)
        lever = pose[:, None, :3, 3] - frames[..., :3, 3]  # (B, N, 3)
        moment = cross(lever, f) + m  # (B, N, 3)
        torque = torch.cat([f.unsqueeze(1) @ rot, moment.unsqueeze(-2) @ rot], -1)  # (B, N, 1, 6) = (J_i^T W)^T
        theta = torque @ self.compliance_t  # (B, N, 1, 6)
        rot_t = rot.transpose(-1, -2)
        # indexing, not squeeze: squeeze of a dynamic shape exports as an ONNX If
        t_base = (theta[..., 0:3] @ rot_t)[..., 0, :]  # (R_i t_i)^T
        r_base = (theta[..., 3:6] @ rot_t)[..., 0, :]
        dp = (t_base + cross(r_base, lever)).sum(1)
        return dp, r_base.sum(1)

    def loaded_pose(self, pose: torch.Tensor, frames: torch.Tensor, wrench: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Loaded TCP position ``(B, 3)`` m and rotation ``(B, 3, 3)``, ``base`` frame."""
        dp, dphi = self(pose, frames, wrench)
        k = skew(dphi)
        rotation = (k + 0.5 * (k @ k)) @ pose[:, :3, :3] + pose[:, :3, :3]
        return pose[:, :3, 3] + dp, rotation
