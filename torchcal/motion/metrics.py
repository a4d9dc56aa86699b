"""Motion quality metrics: path error per sample, joint velocity continuity, peak joint speed.

The *real* path error of a joint trajectory is measured with the robot that executes it: give
the true (or calibrated) parameter vector to :func:`path_errors`, whatever model planned it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel

_DEG = 180.0 / math.pi


def path_errors(
    model: ErrorModel, x: torch.Tensor, q: torch.Tensor, targets: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Position error (m) and orientation error (rad) ``(..., K)`` of joints ``q`` ``(..., K, N)``.

    ``targets`` ``(K, 4, 4)`` are the desired TCP poses, instrument frame; the orientation error is
    the angle of ``R_d R^T``.
    """
    pose = model.tcp_pose(q, x)
    position = (pose[..., :3, 3] - targets[..., :3, 3]).norm(dim=-1)
    rotation = tf.rotation_angle(targets[..., :3, :3] @ pose[..., :3, :3].transpose(-1, -2))
    return position, rotation


def velocity_steps(qdot: torch.Tensor) -> torch.Tensor:
    """``|q_dot(k+1) - q_dot(k)|`` ``(..., K-1, N)``: the jump of joint velocity per cycle, rad/s."""
    return torch.diff(qdot, dim=-2).abs()


def acceleration_steps(qdot: torch.Tensor, dt: float) -> torch.Tensor:
    """``|a(k+1) - a(k)|`` ``(..., K-2, N)`` with ``a = diff(q_dot) / dt``: acceleration continuity, rad/s^2."""
    return torch.diff(torch.diff(qdot, dim=-2) / dt, dim=-2).abs()


@dataclass(frozen=True)
class MotionMetrics:
    """Summary of one joint trajectory against its path (report units: mm, deg, deg/s).

    ``inside`` is the singular neighbourhood (``sigma_min < eps`` of the planning model); a
    quantity over an empty set is reported as ``nan``.
    """

    max_position_error_outside_mm: float
    max_position_error_inside_mm: float
    max_orientation_error_outside_deg: float
    max_orientation_error_inside_deg: float
    rms_position_error_mm: float
    peak_joint_speed_deg_s: list[float]
    peak_speed_ratio: float
    max_velocity_step_deg_s: float
    max_acceleration_step_deg_s2: float
    samples_inside: int
    samples: int
    min_sigma: float

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def _max(values: torch.Tensor) -> float:
    return float(values.max()) if values.numel() else math.nan


def summarize(
    model: ErrorModel,
    x: torch.Tensor,
    q: torch.Tensor,
    qdot: torch.Tensor,
    targets: torch.Tensor,
    sigma_min: torch.Tensor,
    eps: float,
    speed_limits: torch.Tensor,
    dt: float,
) -> MotionMetrics:
    """Metrics of one unbatched trajectory ``q, qdot (K, N)`` executed by the robot ``(model, x)``.

    Args:
        sigma_min: ``(K,)`` singularity measure used to split inside/outside the neighbourhood.
        speed_limits: ``(N,)`` rad/s.
    """
    pos, rot = path_errors(model, x, q, targets)
    inside = sigma_min < eps
    peak = qdot.abs().max(0).values
    return MotionMetrics(
        max_position_error_outside_mm=_max(pos[~inside]) * 1e3,
        max_position_error_inside_mm=_max(pos[inside]) * 1e3,
        max_orientation_error_outside_deg=_max(rot[~inside]) * _DEG,
        max_orientation_error_inside_deg=_max(rot[inside]) * _DEG,
        rms_position_error_mm=float(pos.pow(2).mean().sqrt()) * 1e3,
        peak_joint_speed_deg_s=(peak * _DEG).tolist(),
        peak_speed_ratio=float((peak / speed_limits.to(peak)).max()),
        max_velocity_step_deg_s=float(velocity_steps(qdot).max()) * _DEG,
        max_acceleration_step_deg_s2=float(acceleration_steps(qdot, dt).max()) * _DEG,
        samples_inside=int(inside.sum()),
        samples=int(q.shape[0]),
        min_sigma=float(sigma_min.min()),
    )
