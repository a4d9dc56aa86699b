"""Settings of Cartesian motion generation, with KR6-like defaults.

Joint speed limits: where the robot file gives ``velocity`` per joint they are used; otherwise the
defaults below, close to a KUKA KR 6 R900 sixx datasheet (deg/s per axis A1..A6):
360, 300, 360, 381, 388, 615.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics.robot import RobotModel
from torchcal.motion.dls import DEFAULT_A_MAX, DEFAULT_EPS
from torchcal.motion.path import DEFAULT_RATE_HZ, CartesianLimits

KR6_SPEED_LIMITS_DEG_S = (360.0, 300.0, 360.0, 381.0, 388.0, 615.0)
METHODS = ("dls", "pinv")


@dataclass(frozen=True)
class MotionConfig:
    """Closed-loop inverse kinematics and path settings (SI units).

    Attributes:
        rate_hz: control rate (250 Hz default; 1000 Hz for a 1 kHz interpolator).
        gain: pose-error feedback gain ``K`` (1/s), same for position and orientation; 0 gives
            open-loop integration; ``None`` (default) gives ``K = rate_hz``, i.e. ``K dt = 1``:
            the error seen at a cycle is corrected within that cycle (the fastest setting the
            discrete loop tolerates; ``K dt`` must stay in ``[0, 1]``, above 1 it overshoots).
        method: ``"dls"`` (adaptive damping) or ``"pinv"`` (undamped pseudo-inverse).
        damping_eps: ``sigma_min`` below which damping starts; the singular neighbourhood.
        damping_max: damping factor ``a_max`` at ``sigma_min = 0``.
        selective_damping: damp only the singular values below ``damping_eps`` (see
            :func:`torchcal.motion.dls.dls_inverse`) instead of all by the law of ``sigma_min``.
        speed_limits_deg_s: per-joint speed limits (deg/s); ``None`` = robot file, then KR6 values.
        enforce_speed_limits: scale ``q_dot`` as a whole so no joint exceeds its limit.
        enforce_joint_limits: scale ``q_dot`` so no joint crosses a position limit within a cycle
            (the robot then stops on the limit instead of leaving its range), and clamp.
        null_space_gain: gain of a joint-centering motion projected into the null space of the
            task (``(I - J* J)``); only acts where the robot has redundancy or inside the singular
            neighbourhood, since for 6 joints and a 6-D task the projector vanishes elsewhere.
        profile: speed profile of the path (``trapezoid``, ``scurve``, ``quintic``).
        limits: Cartesian speed/acceleration/jerk limits of the TCP.
        velocity_step_bound_deg_s: documented bound on ``|q_dot(k+1) - q_dot(k)|`` per joint
            (deg/s per cycle) that a continuous joint velocity must respect; checked by metrics.
    """

    rate_hz: float = DEFAULT_RATE_HZ
    gain: float | None = None
    method: str = "dls"
    damping_eps: float = DEFAULT_EPS
    damping_max: float = DEFAULT_A_MAX
    selective_damping: bool = False
    speed_limits_deg_s: tuple[float, ...] | None = None
    enforce_speed_limits: bool = True
    enforce_joint_limits: bool = True
    null_space_gain: float = 0.0
    profile: str = "scurve"
    limits: CartesianLimits = field(default_factory=CartesianLimits)
    velocity_step_bound_deg_s: float = 30.0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ModelError(f"motion method {self.method!r} is not one of {', '.join(METHODS)}")
        if not self.rate_hz > 0.0:
            raise ModelError(f"motion rate_hz must be positive, got {self.rate_hz}")
        if not 0.0 <= self.feedback_gain / self.rate_hz <= 1.0 + 1e-12:
            raise ModelError(
                f"motion gain {self.gain} 1/s at {self.rate_hz} Hz gives gain*dt={self.feedback_gain / self.rate_hz:.3g}; "
                "it must be within [0, 1]"
            )

    @property
    def feedback_gain(self) -> float:
        """``K`` in 1/s (``rate_hz`` when ``gain`` is None)."""
        return self.rate_hz if self.gain is None else float(self.gain)

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz

    def speed_limits(self, robot: RobotModel) -> torch.Tensor:
        """Per-joint speed limits ``(N,)`` in rad/s."""
        if self.speed_limits_deg_s is not None:
            values = torch.tensor(self.speed_limits_deg_s, dtype=torch.float64) * (math.pi / 180.0)
        elif robot.velocity_limits is not None:
            values = robot.velocity_limits.to(torch.float64)
        elif robot.dof == len(KR6_SPEED_LIMITS_DEG_S):
            values = torch.tensor(KR6_SPEED_LIMITS_DEG_S, dtype=torch.float64) * (math.pi / 180.0)
        else:
            raise ModelError(f"{robot.name}: no joint speed limits for {robot.dof} joints; set speed_limits_deg_s")
        if values.shape != (robot.dof,) or not bool((values > 0).all()):
            raise ModelError(f"{robot.name}: need {robot.dof} positive joint speed limits, got {values.tolist()}")
        return values
