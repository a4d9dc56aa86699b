"""Speed profiles (time scalings) ``s(t)`` from rest at ``s = 0`` to rest at ``s = distance``.

* ``trapezoid``: constant acceleration ``+-a_max`` around a cruise at ``v_max``; velocity is
  continuous, acceleration jumps (infinite jerk) at the four phase boundaries.
* ``scurve``: the 7-segment jerk-limited profile (jerk ``+-j_max``, acceleration ``<= a_max``,
  velocity ``<= v_max``); velocity and acceleration are continuous.
* ``quintic``: ``s = D (10 u^3 - 15 u^4 + 6 u^5)``, ``u = t / T``, with the shortest ``T`` that keeps
  the peak speed ``15 D / (8 T)`` and the peak acceleration ``10 D / (sqrt(3) T^2)`` within limits;
  velocity and acceleration are continuous and zero at both ends.

Short moves that cannot reach ``v_max`` (or ``a_max``) get the lower peak that fits. Units are the
caller's: ``distance`` in some unit ``u``, limits in ``u/s``, ``u/s^2``, ``u/s^3``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.core.errors import ModelError

PROFILE_KINDS = ("trapezoid", "scurve", "quintic")


@dataclass(frozen=True)
class SpeedProfile:
    """A rest-to-rest time scaling.

    Attributes:
        kind: one of :data:`PROFILE_KINDS`.
        distance: total travel ``D``.
        duration: total time ``T``, s.
        peak_velocity / peak_acceleration: the values actually reached.
        t_accel: length of the acceleration phase (and of the deceleration phase), s.
        t_jerk: length of each jerk phase of the S-curve (0 for a trapezoid), s.
        jerk: jerk used by the S-curve (``inf`` for a trapezoid).
    """

    kind: str
    distance: float
    duration: float
    peak_velocity: float
    peak_acceleration: float
    t_accel: float = 0.0
    t_jerk: float = 0.0
    jerk: float = math.inf

    def evaluate(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(s, s_dot, s_ddot)`` at times ``t`` (s, any shape); clamped to rest outside ``[0, T]``."""
        t = t.clamp(0.0, self.duration)
        if self.kind == "quintic":
            return self._quintic(t)
        ramp = self.t_accel
        back = (self.duration - t).clamp_min(0.0)
        s_up, v_up, a_up = self._ramp(t.clamp(max=ramp))
        s_dn, v_dn, a_dn = self._ramp(back.clamp(max=ramp))
        cruise_s = 0.5 * self.peak_velocity * ramp + self.peak_velocity * (t - ramp)
        in_up, in_dn = t <= ramp, back <= ramp
        s = torch.where(in_up, s_up, torch.where(in_dn, self.distance - s_dn, cruise_s))
        v = torch.where(in_up, v_up, torch.where(in_dn, v_dn, torch.full_like(t, self.peak_velocity)))
        a = torch.where(in_up, a_up, torch.where(in_dn, -a_dn, torch.zeros_like(t)))
        return s, v, a

    def _ramp(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Acceleration phase ``t in [0, t_accel]`` from rest to ``peak_velocity``."""
        tj, ta, acc, vel = self.t_jerk, self.t_accel, self.peak_acceleration, self.peak_velocity
        jerk = self.jerk if tj > 0 else 0.0
        # jerk-up phase
        s1, v1, a1 = jerk * t**3 / 6.0, jerk * t**2 / 2.0, jerk * t
        # constant-acceleration phase
        dt = t - tj
        s_tj, v_tj = jerk * tj**3 / 6.0, jerk * tj**2 / 2.0
        s2, v2, a2 = s_tj + v_tj * dt + acc * dt**2 / 2.0, v_tj + acc * dt, torch.full_like(t, acc)
        # jerk-down phase, written from its end (point symmetry of the velocity ramp)
        tau = ta - t
        s3, v3, a3 = vel * ta / 2.0 - vel * tau + jerk * tau**3 / 6.0, vel - jerk * tau**2 / 2.0, jerk * tau
        first = t < tj
        last = t >= ta - tj
        s = torch.where(first, s1, torch.where(last, s3, s2))
        v = torch.where(first, v1, torch.where(last, v3, v2))
        a = torch.where(first, a1, torch.where(last, a3, a2))
        return s, v, a

    def _quintic(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        T, D = self.duration, self.distance
        u = t / T
        s = D * (10 * u**3 - 15 * u**4 + 6 * u**5)
        v = D / T * (30 * u**2 - 60 * u**3 + 30 * u**4)
        a = D / T**2 * (60 * u - 180 * u**2 + 120 * u**3)
        return s, v, a


def _check(distance: float, **limits: float) -> None:
    if not math.isfinite(distance) or distance <= 0.0:
        raise ModelError(f"a speed profile needs a positive finite distance, got {distance}")
    for name, value in limits.items():
        if not (value > 0.0) or math.isnan(value):
            raise ModelError(f"a speed profile needs {name} > 0, got {value}")


def trapezoid(distance: float, v_max: float, a_max: float) -> SpeedProfile:
    """Trapezoidal profile (triangular when ``distance < v_max^2 / a_max``)."""
    _check(distance, v_max=v_max, a_max=a_max)
    vel = min(v_max, math.sqrt(a_max * distance))
    ta = vel / a_max
    duration = 2.0 * ta + (distance - vel * ta) / vel
    return SpeedProfile("trapezoid", distance, duration, vel, a_max, t_accel=ta)


def scurve(distance: float, v_max: float, a_max: float, j_max: float) -> SpeedProfile:
    """7-segment jerk-limited profile, with the peak speed lowered when the move is too short."""
    _check(distance, v_max=v_max, a_max=a_max, j_max=j_max)

    def ramp(vel: float) -> tuple[float, float, float]:  # (t_jerk, t_accel, peak acceleration)
        if vel * j_max >= a_max**2:
            return a_max / j_max, a_max / j_max + vel / a_max, a_max
        tj = math.sqrt(vel / j_max)
        return tj, 2.0 * tj, j_max * tj

    vel = v_max
    tj, ta, acc = ramp(vel)
    if vel * ta > distance:  # accelerating and braking alone cover more than the move: lower v
        vel = (-(a_max**2) / j_max + math.sqrt(a_max**4 / j_max**2 + 4.0 * a_max * distance)) / 2.0
        if vel < a_max**2 / j_max:
            vel = (distance * math.sqrt(j_max) / 2.0) ** (2.0 / 3.0)
        tj, ta, acc = ramp(vel)
    duration = 2.0 * ta + max(distance - vel * ta, 0.0) / vel
    return SpeedProfile("scurve", distance, duration, vel, acc, t_accel=ta, t_jerk=tj, jerk=j_max)


def quintic(distance: float, v_max: float, a_max: float) -> SpeedProfile:
    """Quintic polynomial profile (zero velocity and acceleration at both ends)."""
    _check(distance, v_max=v_max, a_max=a_max)
    duration = max(15.0 * distance / (8.0 * v_max), math.sqrt(10.0 * distance / (math.sqrt(3.0) * a_max)))
    return SpeedProfile(
        "quintic",
        distance,
        duration,
        15.0 * distance / (8.0 * duration),
        10.0 * distance / (math.sqrt(3.0) * duration**2),
        t_accel=duration / 2.0,
    )


def make_profile(kind: str, distance: float, v_max: float, a_max: float, j_max: float) -> SpeedProfile:
    """Profile of ``kind`` (one of :data:`PROFILE_KINDS`); ``j_max`` is used by ``scurve`` only."""
    if kind == "trapezoid":
        return trapezoid(distance, v_max, a_max)
    if kind == "scurve":
        return scurve(distance, v_max, a_max, j_max)
    if kind == "quintic":
        return quintic(distance, v_max, a_max)
    raise ModelError(f"unknown speed profile {kind!r} (expected one of {', '.join(PROFILE_KINDS)})")
