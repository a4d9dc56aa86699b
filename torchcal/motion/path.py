"""Cartesian paths (straight line, circular arc) and their time-sampled trajectories.

A path maps a parameter ``lam in [0, 1]`` to a TCP pose ``T_instrument_tool(lam)`` ``(4, 4)``;
positions in m, instrument frame. Orientation goes from the start to the end rotation by slerp
(constant angular velocity axis ``log(R_1 R_0^T)`` in the instrument frame). A speed profile
(:mod:`torchcal.motion.profiles`) over ``lam`` gives the time law; sampling at the control rate
gives desired poses and desired twists ``[v; w]`` (m/s, rad/s, instrument frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics import transforms as tf
from torchcal.motion.profiles import SpeedProfile, make_profile

DEFAULT_RATE_HZ = 250.0
_MAX_SLERP_ANGLE = math.pi - 1e-6


@dataclass(frozen=True)
class CartesianLimits:
    """Cartesian limits of the TCP: linear (m/s, m/s^2, m/s^3) and angular (rad/s, ...)."""

    linear_speed: float = 0.25
    linear_accel: float = 1.0
    linear_jerk: float = 10.0
    angular_speed: float = 1.0
    angular_accel: float = 4.0
    angular_jerk: float = 40.0


def slerp(r0: torch.Tensor, r1: torch.Tensor, lam: torch.Tensor) -> torch.Tensor:
    """Rotations ``(..., 3, 3)`` from ``r0`` to ``r1`` (both ``(3, 3)``) at fractions ``lam`` ``(...)``."""
    axis_angle = tf.so3_log(r1 @ r0.transpose(-1, -2))
    return tf.so3_exp(lam.unsqueeze(-1) * axis_angle) @ r0


class CartesianPath:
    """Base class: start/end poses, slerped orientation, a position curve given by subclasses."""

    def __init__(self, start: torch.Tensor, end: torch.Tensor) -> None:
        if start.shape != (4, 4) or end.shape != (4, 4):
            raise ModelError(f"path poses must be (4, 4), got {tuple(start.shape)} and {tuple(end.shape)}")
        self.start = start.to(torch.float64)
        self.end = end.to(self.start)
        self.rotation_vector = tf.so3_log(self.end[:3, :3] @ self.start[:3, :3].T)
        self.angle = float(self.rotation_vector.norm())
        if self.angle > _MAX_SLERP_ANGLE:
            raise ModelError(f"path rotates by {math.degrees(self.angle):.3f} deg; slerp needs less than 180 deg")

    @property
    def length(self) -> float:
        """Length of the position curve, m."""
        raise NotImplementedError

    def positions(self, lam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Positions ``(..., 3)`` and ``d p / d lam`` ``(..., 3)`` (m) at ``lam`` ``(...)``."""
        raise NotImplementedError

    def poses(self, lam: torch.Tensor) -> torch.Tensor:
        """TCP poses ``(..., 4, 4)`` at ``lam`` ``(...)``."""
        p, _ = self.positions(lam)
        return tf.homogeneous(slerp(self.start[:3, :3], self.end[:3, :3], lam), p)

    def tangent(self, lam: torch.Tensor) -> torch.Tensor:
        """``d(pose)/d lam`` as a twist ``[v; w]`` ``(..., 6)`` (m, rad per unit ``lam``)."""
        _, dp = self.positions(lam)
        return torch.cat([dp, self.rotation_vector.expand_as(dp)], -1)

    def profile(self, kind: str = "trapezoid", limits: CartesianLimits | None = None) -> SpeedProfile:
        """Time law of ``lam`` over ``[0, 1]`` respecting both the linear and angular limits."""
        limits = limits or CartesianLimits()
        scales = []  # path quantity per unit lam, with its limits
        if self.length > 0.0:
            scales.append((self.length, limits.linear_speed, limits.linear_accel, limits.linear_jerk))
        if self.angle > 0.0:
            scales.append((self.angle, limits.angular_speed, limits.angular_accel, limits.angular_jerk))
        if not scales:
            raise ModelError("the path neither moves nor rotates the TCP")
        v = min(sv / s for s, sv, _, _ in scales)
        a = min(sa / s for s, _, sa, _ in scales)
        j = min(sj / s for s, _, _, sj in scales)
        return make_profile(kind, 1.0, v, a, j)

    def sample(
        self, profile: str | SpeedProfile = "trapezoid", limits: CartesianLimits | None = None, rate_hz: float = DEFAULT_RATE_HZ
    ) -> CartesianTrajectory:
        """Desired poses and twists at ``rate_hz`` from start to end (last sample at the end pose)."""
        if not rate_hz > 0.0:
            raise ModelError(f"control rate must be positive, got {rate_hz} Hz")
        law = profile if isinstance(profile, SpeedProfile) else self.profile(profile, limits)
        dt = 1.0 / rate_hz
        steps = math.ceil(law.duration / dt - 1e-9)
        t = torch.arange(steps + 1, dtype=torch.float64, device=self.start.device) * dt
        lam, lam_dot, _ = law.evaluate(t)
        return CartesianTrajectory(
            t=t,
            poses=self.poses(lam),
            twists=self.tangent(lam) * lam_dot.unsqueeze(-1),
            lam=lam,
            rate_hz=float(rate_hz),
        )


class LinePath(CartesianPath):
    """Straight line from ``start`` to ``end`` (``(4, 4)`` TCP poses, m, instrument frame)."""

    def __init__(self, start: torch.Tensor, end: torch.Tensor) -> None:
        super().__init__(start, end)
        self.delta = self.end[:3, 3] - self.start[:3, 3]

    @property
    def length(self) -> float:
        return float(self.delta.norm())

    def positions(self, lam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lam = lam.to(self.start)
        p = self.start[:3, 3] + lam.unsqueeze(-1) * self.delta
        return p, self.delta.expand_as(p)


class ArcPath(CartesianPath):
    """Circular arc from ``start`` through the point ``via`` ``(3,)`` to ``end`` (KUKA CIRC style).

    The arc runs the way that passes ``via``; center, radius and axis follow from the three points.
    """

    def __init__(self, start: torch.Tensor, via: torch.Tensor, end: torch.Tensor) -> None:
        super().__init__(start, end)
        p0, pv, p1 = self.start[:3, 3], via.to(self.start), self.end[:3, 3]
        a, b = pv - p0, p1 - p0
        normal = torch.linalg.cross(a, b)
        n2 = float(normal @ normal)
        scale = max(float(a.norm()), float(b.norm()), 1e-12)
        if n2 <= (1e-9 * scale**2) ** 2:
            raise ModelError("arc start, via and end points are collinear (or coincide); use a line")
        self.center = p0 + torch.linalg.cross(float(a @ a) * b - float(b @ b) * a, normal) / (2.0 * n2)
        self.axis = normal / math.sqrt(n2)
        self.r0 = p0 - self.center
        self.radius = float(self.r0.norm())
        r1 = p1 - self.center
        # p0 -> via -> p1 is counter-clockwise about ``axis`` = (via - p0) x (p1 - p0)
        phi = math.atan2(float(self.axis @ torch.linalg.cross(self.r0, r1)), float(self.r0 @ r1))
        self.sweep = phi if phi > 0.0 else phi + 2.0 * math.pi

    @property
    def length(self) -> float:
        return self.radius * self.sweep

    def positions(self, lam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lam = lam.to(self.start)
        rot = tf.so3_exp(lam.unsqueeze(-1) * self.sweep * self.axis)
        r = (rot @ self.r0.unsqueeze(-1)).squeeze(-1)
        return self.center + r, self.sweep * torch.linalg.cross(self.axis.expand_as(r), r, dim=-1)


@dataclass(frozen=True)
class CartesianTrajectory:
    """Desired TCP motion sampled at ``rate_hz``.

    Attributes:
        t: ``(K,)`` sample times, s.
        poses: ``(K, 4, 4)`` desired ``T_instrument_tool``.
        twists: ``(K, 6)`` desired ``[v; w]`` (m/s, rad/s), instrument frame.
        lam: ``(K,)`` path parameter.
        rate_hz: control rate, Hz.
    """

    t: torch.Tensor
    poses: torch.Tensor
    twists: torch.Tensor
    lam: torch.Tensor
    rate_hz: float

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz

    def __len__(self) -> int:
        return int(self.t.shape[0])
