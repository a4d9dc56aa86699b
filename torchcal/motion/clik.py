"""Closed-loop inverse kinematics (CLIK) along a sampled Cartesian trajectory.

At each control cycle ``k`` (period ``dt``)::

    e_k    = [p_d - p ; log(R_d R^T)]                      pose error (axis-angle), instrument frame
    v_ff,k = [p_d,k+1 - p_d,k ; log(R_d,k+1 R_d,k^T)] / dt  feed-forward twist
    q_dot  = J*(q_k) (v_ff,k + K e_k)  [+ (I - J* J) q_dot_0]
    q_k+1  = q_k + dt * s_k * q_dot                          s_k in [0, 1]: limit scaling

* ``J*`` is the adaptive-damping DLS inverse (:mod:`torchcal.motion.dls`) or, for comparison, the
  undamped pseudo-inverse.
* The feed-forward is the secant of the desired trajectory over the cycle rather than its
  instantaneous twist: with Euler integration the instantaneous twist lags by ``a dt^2 / 2`` every
  cycle, which the feedback would turn into a steady error of ``a dt / (2 K)``.
* ``e_o = log(R_d R^T)`` is the axis-angle error ``theta * r``; near zero it equals the
  ``r sin(theta)`` of the classical formulation.
* Limits: ``s_k`` is the largest factor ``<= 1`` with which no joint exceeds its speed limit and
  no joint leaves its position range within the cycle. Scaling the whole ``q_dot`` keeps its
  direction, so the TCP stays on the path and only falls behind; the feedback then catches up.
  A joint already on a limit and pushed further stops the robot (``s_k = 0``): the result's
  ``limited`` flags such cycles. ``q`` is finally clamped into its range against round-off.
* The optional null-space motion ``q_dot_0 = -k0 W^-2 (q - q_mid)`` (``W`` the joint ranges)
  centres the joints where the task leaves freedom.

Works with any :class:`ErrorModel` parameter vector ``x``: given the calibrated ``x``, the joint
trajectory is the one the *real* robot must be sent to put its TCP on the path.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import pose_error
from torchcal.kinematics.mdh import chain_transforms
from torchcal.motion.config import MotionConfig
from torchcal.motion.dls import DLSInverse, dls_inverse, pseudo_inverse
from torchcal.motion.path import CartesianTrajectory
from torchcal.motion.trajectory import JointTrajectory


@dataclass(frozen=True)
class CLIKResult:
    """Joint trajectory and per-cycle diagnostics (leading dims ``...`` of ``q0``, ``K`` cycles).

    Attributes:
        trajectory: joints ``q`` ``(..., K, N)`` rad and velocities ``qdot`` ``(..., K, N)`` rad/s.
        error: ``(..., K, 6)`` model pose error ``[m, rad]`` at each cycle before its update.
        sigma_min: ``(..., K)`` smallest singular value of ``J`` (the singularity measure).
        manipulability: ``(..., K)`` ``prod(sigma)``.
        damping_sq: ``(..., K)`` damping ``a^2`` applied.
        scale: ``(..., K)`` limit scaling factor ``s_k`` applied to ``q_dot``.
        limited: ``(..., K)`` True where a joint position limit reduced ``s_k``.
    """

    trajectory: JointTrajectory
    error: torch.Tensor
    sigma_min: torch.Tensor
    manipulability: torch.Tensor
    damping_sq: torch.Tensor
    scale: torch.Tensor
    limited: torch.Tensor


class _FixedModel:
    """Pose and geometric Jacobian of ``(model, x)`` for a fixed ``x``, with one chain pass per call.

    Same quantities as :func:`torchcal.kinematics.joint_jacobian.geometric_jacobian` (rows
    ``[v; w]``, instrument frame); the ``x``-only transforms are computed once, which matters in
    a loop of thousands of control cycles.
    """

    def __init__(self, model: ErrorModel, x: torch.Tensor) -> None:
        self.table = model.table(x)
        self.world = model.instrument_from_base(x) @ model.T_base_0.to(x)
        self.tail = model.T_n_flange.to(x) @ model.flange_from_tool(x)

    def __call__(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rot, pos = chain_transforms(q, self.table, all_frames=True)
        r_w, p_w = self.world[:3, :3], self.world[:3, 3]
        axes = torch.einsum("ij,...nj->...ni", r_w, rot[..., :, :, 2])
        origins = torch.einsum("ij,...nj->...ni", r_w, pos) + p_w
        last = tf.homogeneous(rot[..., -1, :, :], pos[..., -1, :])
        pose = self.world @ last @ self.tail
        lever = pose[..., None, :3, 3] - origins
        linear = torch.linalg.cross(axes, lever, dim=-1)
        return pose, torch.cat([linear, axes], -1).transpose(-1, -2)


def feed_forward(traj: CartesianTrajectory) -> torch.Tensor:
    """Secant twists ``(K, 6)`` of the desired poses (m/s, rad/s); zero on the last sample."""
    poses = traj.poses
    dp = poses[1:, :3, 3] - poses[:-1, :3, 3]
    dr = tf.so3_log(poses[1:, :3, :3] @ poses[:-1, :3, :3].transpose(-1, -2))
    twist = torch.cat([dp, dr], -1) / traj.dt
    return torch.cat([twist, torch.zeros_like(twist[:1])], 0)


def limit_scale(
    qdot: torch.Tensor, q: torch.Tensor, dt: float, speed: torch.Tensor | None, bounds: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Largest ``s in [0, 1]`` ``(...)`` keeping ``s * qdot`` within speed and position limits.

    Args:
        qdot: ``(..., N)`` joint velocities, rad/s.
        q: ``(..., N)`` current joints, rad.
        speed: ``(N,)`` speed limits, rad/s, or None.
        bounds: ``(N, 2)`` joint limits, rad, or None.

    Returns:
        ``(s, position_limited)``, both ``(...)``.
    """
    big = torch.full_like(qdot, torch.inf)
    ratio_speed = big if speed is None else speed / qdot.abs().clamp_min(1e-300)
    if bounds is None:
        ratio_pos = big
    else:
        room_hi = ((bounds[:, 1] - q) / dt).clamp_min(0.0)
        room_lo = ((q - bounds[:, 0]) / dt).clamp_min(0.0)
        room = torch.where(qdot > 0, room_hi, room_lo)
        ratio_pos = torch.where(qdot != 0, room / qdot.abs().clamp_min(1e-300), big)
    s_speed = ratio_speed.amin(-1).clamp(max=1.0)
    s_pos = ratio_pos.amin(-1).clamp(max=1.0)
    return torch.minimum(s_speed, s_pos), s_pos < s_speed


def follow(
    model: ErrorModel,
    x: torch.Tensor,
    traj: CartesianTrajectory,
    q0: torch.Tensor,
    config: MotionConfig | None = None,
) -> CLIKResult:
    """Run CLIK along ``traj`` from joints ``q0`` ``(..., N)`` rad with the model ``(model, x)``.

    ``traj`` must be sampled at ``config.rate_hz``. The loop over cycles is sequential by nature;
    each cycle is batched over the leading dims of ``q0``.
    """
    config = config or MotionConfig()
    if abs(traj.rate_hz - config.rate_hz) > 1e-9 * config.rate_hz:
        raise ModelError(f"trajectory sampled at {traj.rate_hz} Hz but the motion config runs at {config.rate_hz} Hz")
    robot = model.robot
    if q0.shape[-1] != robot.dof:
        raise ModelError(f"q0 has {q0.shape[-1]} joints, {robot.name} has {robot.dof}")
    dt = config.dt
    speed = config.speed_limits(robot).to(q0) if config.enforce_speed_limits else None
    bounds = robot.joint_limits.to(q0) if config.enforce_joint_limits else None
    # the null-space pull towards mid-range; a continuous joint (infinite span) has no middle: weight 0
    centre = robot.turn_limits.to(q0).mean(-1)
    weight = 1.0 / (robot.joint_limits[:, 1] - robot.joint_limits[:, 0]).to(q0) ** 2
    ff = feed_forward(traj).to(q0)
    targets = traj.poses.to(q0)
    eye = torch.eye(robot.dof, dtype=q0.dtype, device=q0.device)

    kinematics = _FixedModel(model, x.to(q0))
    q = q0.clone()
    out_q, out_qd, out_e, out_s, out_m, out_a, out_scale, out_lim = ([] for _ in range(8))
    for k in range(len(traj)):
        pose, jac = kinematics(q)
        err = pose_error(targets[k], pose)
        inv: DLSInverse = (
            dls_inverse(jac, config.damping_eps, config.damping_max, config.selective_damping) if config.method == "dls" else pseudo_inverse(jac)
        )
        qdot = (inv.inverse @ (ff[k] + config.feedback_gain * err).unsqueeze(-1)).squeeze(-1)
        if config.null_space_gain > 0.0:
            q_dot_0 = -config.null_space_gain * weight * (q - centre)
            qdot = qdot + ((eye - inv.inverse @ jac) @ q_dot_0.unsqueeze(-1)).squeeze(-1)
        scale, limited = limit_scale(qdot, q, dt, speed, bounds)
        qdot = qdot * scale.unsqueeze(-1)
        out_q.append(q)
        out_qd.append(qdot)
        out_e.append(err)
        out_s.append(inv.sigma_min)
        out_m.append(inv.manipulability)
        out_a.append(inv.damping_sq)
        out_scale.append(scale)
        out_lim.append(limited & (scale < 1.0))
        q = q + dt * qdot
        if bounds is not None:
            q = torch.maximum(torch.minimum(q, bounds[:, 1]), bounds[:, 0])

    stack = lambda items, dim: torch.stack(items, dim)  # noqa: E731
    tdim = q0.dim() - 1  # time axis sits after the batch dims
    return CLIKResult(
        trajectory=JointTrajectory(t=traj.t.to(q0), q=stack(out_q, tdim), qdot=stack(out_qd, tdim), rate_hz=traj.rate_hz),
        error=stack(out_e, tdim),
        sigma_min=stack(out_s, -1),
        manipulability=stack(out_m, -1),
        damping_sq=stack(out_a, -1),
        scale=stack(out_scale, -1),
        limited=stack(out_lim, -1),
    )
