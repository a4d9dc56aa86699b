"""Deflection compensation by target offsetting: command a pose that the load bends onto the target.

Iteration (per pose, batched)::

    T_off(0)   = T_d
    q(n)       = IK(T_off(n))                          rigid model, warm-started
    T_def(n)   = FK_deformed(q(n), W)                  springs under the expected wrench
    T_off(n+1) = T_off(n) + (T_d - T_def(n))           position: vector sum;
                                                       orientation: R_off <- exp(log(R_d R_def^T)) R_off

until the remaining position (and rotation) error is below tolerance. The result is the joint
command ``q`` whose *loaded* TCP is at ``T_d``. The deformed FK is the exact deformed chain of
:mod:`torchcal.stiffness.deformed`, so the iteration also removes the second-order terms the VJM
law leaves out. Each update is a fixed-point step with contraction factor of the order of the
deflection's relative change over the offset (about 1e-3), so a few iterations suffice.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import solve_ik
from torchcal.stiffness.deformed import loaded_tcp_pose
from torchcal.stiffness.vjm import WrenchFrame


@dataclass(frozen=True)
class DeflectionCompensation:
    """Result of :func:`compensate_deflection`.

    Attributes:
        q: ``(..., N)`` compensated joint command, rad.
        target_offset: ``(..., 4, 4)`` the offset target ``T_off`` handed to the rigid IK.
        position_error: ``(...,)`` predicted loaded TCP position error left, m.
        rotation_error: ``(...,)`` predicted loaded TCP rotation error left, rad (0 if position only).
        iterations: offset updates performed.
        converged: ``(...,)`` both errors below tolerance and the last rigid IK converged (near a
            singularity it may not: check this before sending ``q``).
    """

    q: torch.Tensor
    target_offset: torch.Tensor
    position_error: torch.Tensor
    rotation_error: torch.Tensor
    iterations: int
    converged: torch.Tensor


def compensate_deflection(
    model: ErrorModel,
    x: torch.Tensor,
    compliance: torch.Tensor,
    target: torch.Tensor,
    wrench: torch.Tensor,
    q0: torch.Tensor,
    *,
    wrench_frame: WrenchFrame = "tool",
    position_only: bool = False,
    position_tol_m: float = 1e-7,
    rotation_tol_rad: float = 1e-7,
    max_iterations: int = 20,
    equilibrium_iterations: int = 2,
) -> DeflectionCompensation:
    """Joint command whose TCP, bent by ``wrench``, lands on ``target``.

    Args:
        model, x: the (calibrated) rigid geometry and its ``instrument`` frame.
        compliance: ``(N, 6, 6)`` joint compliance (e.g. ``StiffnessEstimate.compliance``).
        target: ``(..., 4, 4)`` desired ``T_instrument_tool``, m.
        wrench: ``(..., 6)`` expected wrench at the TCP (N, N m), in ``wrench_frame``.
        q0: ``(..., N)`` starting joints (the nominal command), rad.
        position_only: offset and check the position only (the orientation is left as the rigid
            IK of the position target gives it, starting from ``q0``).
        equilibrium_iterations: spring equilibrium iterations of the deformed FK.
    """
    compliance = compliance.to(target)
    p_d, r_d = target[..., :3, 3], target[..., :3, :3]
    offset = target.clone()
    q = q0.clone()
    done = torch.zeros(target.shape[:-2], dtype=torch.bool, device=target.device)
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 (read after the loop)
        ik_target = offset[..., :3, 3] if position_only else offset
        ik = solve_ik(model, x, ik_target, q, position_only=position_only)
        q = ik.q
        loaded, _ = loaded_tcp_pose(
            model, q, x, compliance, wrench, wrench_frame=wrench_frame, iterations=equilibrium_iterations
        )
        dp = p_d - loaded[..., :3, 3]
        dr = tf.so3_log(r_d @ loaded[..., :3, :3].transpose(-1, -2))
        perr = dp.norm(dim=-1)
        rerr = torch.zeros_like(perr) if position_only else dr.norm(dim=-1)
        done = (perr < position_tol_m) & (rerr < rotation_tol_rad) & ik.converged
        if bool(done.all()):
            break
        step = (~done).to(dp.dtype).unsqueeze(-1)
        offset = offset.clone()
        offset[..., :3, 3] = offset[..., :3, 3] + dp * step
        if not position_only:
            offset[..., :3, :3] = tf.so3_exp(dr * step) @ offset[..., :3, :3]
    return DeflectionCompensation(
        q=q, target_offset=offset, position_error=perr, rotation_error=rerr, iterations=iterations, converged=done
    )


class DeflectionCompensator:
    """Nominal joint command + expected wrench -> compensated joint command.

    The stage a composed compensator chains after geometry: the target is the TCP pose the
    command reaches on the unloaded (calibrated) robot.

    Args:
        model, x: calibrated rigid geometry.
        compliance: ``(N, 6, 6)`` joint compliance.
        wrench_frame: frame of the wrenches passed to :meth:`__call__`.
    """

    def __init__(
        self,
        model: ErrorModel,
        x: torch.Tensor,
        compliance: torch.Tensor,
        *,
        wrench_frame: WrenchFrame = "tool",
        position_only: bool = False,
        max_iterations: int = 20,
    ) -> None:
        self.model, self.x, self.compliance = model, x, compliance
        self.wrench_frame = wrench_frame
        self.position_only = position_only
        self.max_iterations = max_iterations

    def __call__(self, q_command: torch.Tensor, wrench: torch.Tensor) -> DeflectionCompensation:
        """Compensate ``q_command`` ``(..., N)`` rad for ``wrench`` ``(..., 6)`` (N, N m)."""
        target = self.model.tcp_pose(q_command, self.x)
        return compensate_deflection(
            self.model,
            self.x,
            self.compliance,
            target,
            wrench,
            q_command,
            wrench_frame=self.wrench_frame,
            position_only=self.position_only,
            max_iterations=self.max_iterations,
        )
