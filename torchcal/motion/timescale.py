"""Time law of a geometric joint path: the fastest ``s(t)`` within speed and acceleration limits.

Given joints ``q(s)`` along the path parameter ``s`` (m) with derivatives ``q'(s)``, ``q''(s)`` on a
grid, the joint velocity and acceleration are ``q' s_dot`` and ``q' s_ddot + q'' s_dot^2``. With
``x = s_dot^2`` every limit is linear in ``(s_ddot, x)``::

    x <= v_path^2                            path speed (module waypoints: TCP speed and turn rate)
    |q'_j| sqrt(x) <= V_j                    joint speed
    |q'_j s_ddot + q''_j x| <= A_j           joint acceleration
    |s_ddot| <= a_path                       path acceleration

so the admissible ``s_ddot`` at ``(s, x)`` is an interval, non-empty up to a largest ``x`` (the
maximum velocity curve, computed here in closed form from every pair of bounds). The profile is
the classical phase-plane construction on the grid (Bobrow, Dubowsky and Gibson; Pham's TOPP):
a forward pass at the largest acceleration from ``x = 0``, capped by the velocity curve, then a
backward pass at the largest deceleration from ``x = 0`` at the end, keeping the smaller ``x``.
``s_ddot`` is constant between grid points, so ``s(t)`` is piecewise quadratic and the time of
each grid interval is ``2 h / (s_dot_i + s_dot_i+1)``.

The path never changes: limits are met by going slower along it, never by leaving it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from torchcal.core.errors import ModelError

_TINY = 1e-12


@dataclass(frozen=True)
class TimeLaw:
    """``s(t)`` on the grid: ``s`` ``(G,)`` m, ``s_dot`` ``(G,)`` m/s, ``t`` ``(G,)`` s at each grid point."""

    s: np.ndarray
    s_dot: np.ndarray
    t: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def sample(self, times: np.ndarray) -> np.ndarray:
        """``s`` ``(K,)`` at ``times`` ``(K,)`` s (constant ``s_ddot`` within each grid interval)."""
        times = np.clip(times, 0.0, self.duration)
        i = np.clip(np.searchsorted(self.t, times, side="right") - 1, 0, len(self.s) - 2)
        h = self.s[i + 1] - self.s[i]
        v0, v1 = self.s_dot[i], self.s_dot[i + 1]
        acc = (v1**2 - v0**2) / (2.0 * h)
        tau = times - self.t[i]
        return np.minimum(self.s[i] + v0 * tau + 0.5 * acc * tau**2, self.s[i + 1])

    def stretched(self, factor: float) -> TimeLaw:
        """The same path ``factor >= 1`` times slower (speeds / factor, accelerations / factor^2)."""
        return TimeLaw(self.s, self.s_dot / factor, self.t * factor)


def _accel_bounds(a: np.ndarray, b: np.ndarray, limit: np.ndarray, path_accel: float):
    """Coefficients of the lower/upper bounds ``alpha + beta x`` of ``s_ddot`` ``(G, C)``."""
    g = a.shape[0]
    big = np.abs(a) > _TINY
    safe = np.where(big, a, 1.0)
    lo_a = np.where(big, -limit / np.abs(safe), -np.inf)
    hi_a = np.where(big, limit / np.abs(safe), np.inf)
    beta = np.where(big, -b / safe, 0.0)
    lo_alpha = np.concatenate([lo_a, np.full((g, 1), -path_accel)], 1)
    hi_alpha = np.concatenate([hi_a, np.full((g, 1), path_accel)], 1)
    betas = np.concatenate([beta, np.zeros((g, 1))], 1)
    return lo_alpha, hi_alpha, betas


def velocity_curve(dq: np.ndarray, ddq: np.ndarray, speed: float, path_accel: float,
                   joint_speed: np.ndarray, joint_accel: np.ndarray) -> np.ndarray:
    """Largest admissible ``x = s_dot^2`` ``(G,)`` at each grid point (module docstring)."""
    x = np.full(dq.shape[0], speed**2)
    moving = np.abs(dq) > _TINY
    with np.errstate(divide="ignore", over="ignore"):
        x = np.minimum(x, np.min(np.where(moving, (joint_speed / np.where(moving, np.abs(dq), 1.0)) ** 2, np.inf), 1))
        # a joint that does not move with s but is curved (q' = 0, q'' != 0): |q''| x <= A
        flat = (np.abs(dq) <= _TINY) & (np.abs(ddq) > _TINY)
        x = np.minimum(x, np.min(np.where(flat, joint_accel / np.abs(np.where(flat, ddq, 1.0)), np.inf), 1))
    lo_alpha, hi_alpha, beta = _accel_bounds(dq, ddq, joint_accel, path_accel)
    # lower bound j <= upper bound k for every pair: (lo_j - hi_k) + (beta_j - beta_k) x <= 0
    gap0 = lo_alpha[:, :, None] - hi_alpha[:, None, :]
    slope = beta[:, :, None] - beta[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        cap = np.where((slope > _TINY) & np.isfinite(gap0), -gap0 / slope, np.inf)
    return np.minimum(x, cap.reshape(cap.shape[0], -1).min(1))


def _interval(dq_i, ddq_i, x, joint_accel, path_accel) -> tuple[float, float]:
    lo_alpha, hi_alpha, beta = _accel_bounds(dq_i[None], ddq_i[None], joint_accel, path_accel)
    lo = float(np.max(lo_alpha[0] + beta[0] * x))
    hi = float(np.min(hi_alpha[0] + beta[0] * x))
    return lo, hi


def time_optimal(s: np.ndarray, dq: np.ndarray, ddq: np.ndarray, *, speed: float, path_accel: float,
                 joint_speed: np.ndarray, joint_accel: np.ndarray, stops: np.ndarray | None = None) -> TimeLaw:
    """Fastest time law along ``s`` ``(G,)`` for ``q'`` ``dq`` and ``q''`` ``ddq`` ``(G, N)`` (per m).

    Args:
        speed: path speed limit, m/s; ``path_accel`` its acceleration limit, m/s^2.
        joint_speed, joint_accel: ``(N,)`` limits, rad/s and rad/s^2.
        stops: indices of grid points where the path must stop (waypoint corners); the first and
            the last point always stop.

    Raises:
        ModelError: a limit that is not positive and finite.
    """
    for name, value in (("speed", speed), ("path acceleration", path_accel)):
        if not (value > 0.0 and math.isfinite(value)):
            raise ModelError(f"{name} limit must be positive and finite, got {value}")
    for name, values in (("joint speed", joint_speed), ("joint acceleration", joint_accel)):
        if not (np.all(values > 0.0) and np.all(np.isfinite(values))):
            raise ModelError(f"{name} limits must be positive and finite, got {values.tolist()}")
    n = len(s)
    h = np.diff(s)
    cap = velocity_curve(dq, ddq, speed, path_accel, joint_speed, joint_accel)
    cap[0] = cap[-1] = 0.0
    if stops is not None:
        cap[stops] = 0.0
    x = np.empty(n)
    x[0] = 0.0
    # Where the grid cannot honour a bound exactly (the interval empties between grid points) the
    # passes keep the speed instead of stopping; the caller measures the samples and stretches time.
    for i in range(n - 1):  # forward: largest acceleration, capped by the velocity curve
        _, hi = _interval(dq[i], ddq[i], x[i], joint_accel, path_accel)
        reached = x[i] + 2.0 * h[i] * hi
        x[i + 1] = min(cap[i + 1], reached if reached > 0.0 else x[i])
    for i in range(n - 2, -1, -1):  # backward: largest deceleration into the next point
        lo, _ = _interval(dq[i + 1], ddq[i + 1], x[i + 1], joint_accel, path_accel)
        allowed = x[i + 1] - 2.0 * h[i] * lo
        x[i] = min(x[i], allowed if allowed > 0.0 else x[i + 1])
    if n > 2:  # interior points keep some speed, so every interval takes a finite time
        floor = 1e-6 * float(np.max(x))
        x[1:-1] = np.maximum(x[1:-1], floor)
    s_dot = np.sqrt(np.maximum(x, 0.0))
    with np.errstate(divide="ignore"):
        dt = 2.0 * h / (s_dot[1:] + s_dot[:-1])
    if not np.all(np.isfinite(dt)):
        raise ModelError("the time law stalls on the path (a joint limit admits no speed there)")
    return TimeLaw(s=s, s_dot=s_dot, t=np.concatenate([[0.0], np.cumsum(dt)]))
