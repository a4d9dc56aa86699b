"""Joint trajectory of a waypoint path: position-first geometry, then a time law, then the samples.

1. The first waypoint is solved from the start joints (full pose, position-first steps).
2. Each segment (waypoint to waypoint) is followed in its path parameter ``s`` on a fine grid by
   the position-first task-priority step (:mod:`torchcal.motion.priority`): joints ``q(s)``.
3. ``q(s)`` is interpolated by a cubic spline per segment; its ``q'(s)``, ``q''(s)`` give the time law
   (:mod:`torchcal.motion.timescale`) that keeps every joint within its speed and acceleration
   limits and the TCP within the path speed and acceleration, stopping at every waypoint.
4. The total time is stretched to a whole number of periods ``dt``; at each sample ``t_k = k dt``
   the joints are the spline at ``s(t_k)`` followed by a minimum-norm position correction onto
   the path point, so the position is exact at every sample while the velocity stays that of
   ``q(s) s_dot`` (the correction is of the order of the spline's interpolation error).
5. The samples are measured by finite differences (speeds, accelerations) and forward kinematics
   (path error, orientation deviation); the rare overshoot of a limit left by the grid is removed
   by stretching time, never by moving off the path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.robot import RobotModel
from torchcal.motion.config import KR6_SPEED_LIMITS_DEG_S
from torchcal.motion.priority import (
    PrioritySettings,
    TcpKinematics,
    correct_position,
    follow_geometric,
    priority_step,
)
from torchcal.motion.timescale import TimeLaw, time_optimal
from torchcal.motion.waypoints import WaypointPath

DEG = math.pi / 180.0
DEFAULT_JOINT_ACCEL_DEG_S2 = 3000.0
MAX_SAMPLES = 1_000_000
#: Most points of the geometric pass's grid over the whole path (each is a Newton solve).
MAX_GRID_POINTS = 1_000_000


@dataclass
class PlanOptions:
    """Options of ``torchcal motion`` (units of the files: mm, deg, s).

    Attributes:
        start: joints the motion starts from, deg (one per joint; required); the first waypoint is
            solved from there.
        speed: TCP speed along the path, mm/s.
        accel: TCP acceleration along the path, mm/s^2.
        angular_speed: largest tool turn rate between waypoints, deg/s.
        dt: interpolation period of the output, s.
        joint_speed: joint speed limits, deg/s (empty: the robot file's ``velocity``, else KR6-like values).
        joint_accel: joint acceleration limits, deg/s^2 (empty: the robot file's ``acceleration``,
            else 3000 for every joint).
        step: grid step of the geometric pass along the path, mm.
        orientation_eps: singular value of the orientation task (in the position task's null
            space) below which the orientation yields, rad/rad.
        orientation_damping: damping of the orientation task where its singular value is zero, rad/rad.
        position_eps: singular value of the position task below which the position yields (the
            TCP at the edge of its reach), mm/rad.
        position_damping: damping of the position task where its singular value is zero, mm/rad.
        gain: orientation-error feedback per mm of path, 1/mm (recovers a yielded orientation over about 1/gain mm).
        tolerance: largest path error accepted at a sample, mm; beyond it the command writes the
            report but no trajectory.
        between_tolerance: largest path error accepted halfway between two samples, where a
            controller interpolating the joints linearly puts the TCP, mm (default 0.02: below the
            0.03 mm an arm repeats to; near a singularity the joints turn fast and 4 ms samples
            leave about 0.01 mm there).
    """

    start: list[float] = field(default_factory=list)
    speed: float = 250.0
    accel: float = 2000.0
    angular_speed: float = 90.0
    dt: float = 0.004
    joint_speed: list[float] = field(default_factory=list)
    joint_accel: list[float] = field(default_factory=list)
    step: float = 0.5
    orientation_eps: float = 0.05
    orientation_damping: float = 0.05
    position_eps: float = 20.0
    position_damping: float = 10.0
    gain: float = 1.0
    tolerance: float = 0.005
    between_tolerance: float = 0.02

    def check(self, robot: RobotModel) -> None:
        """Refuse a value out of range, with one line naming the option."""
        from torchcal.core.overrides import check_range

        for name in ("speed", "accel", "angular_speed", "dt", "step", "orientation_eps", "position_eps", "gain",
                     "tolerance", "between_tolerance"):
            check_range(self, name, low=0.0, low_open=True)
        check_range(self, "orientation_damping", low=0.0)
        check_range(self, "position_damping", low=0.0)
        if self.gain * self.step > 1.0:
            raise ModelError(f"gain * step must be at most 1 (the whole error in one step), got "
                             f"{self.gain:g} 1/mm * {self.step:g} mm; lower step")
        if not self.start:
            raise ModelError(f"start=[q1,...,q{robot.dof}] (deg) is required: the joints the motion starts from")
        for name in ("start", "joint_speed", "joint_accel"):
            values = getattr(self, name)
            if values and len(values) != robot.dof:
                raise ModelError(f"{name} has {len(values)} values, robot '{robot.name}' has {robot.dof} joints")
            if not all(math.isfinite(v) for v in values):
                raise ModelError(f"{name} holds a value that is not a finite number: {values}")
        for name in ("joint_speed", "joint_accel"):
            if any(v <= 0 for v in getattr(self, name)):
                raise ModelError(f"{name} limits must be positive, got {getattr(self, name)}")
        limits = torch.rad2deg(robot.joint_limits.to(torch.float64)).tolist()
        for j, (value, (low, high)) in enumerate(zip(self.start, limits, strict=True)):
            if not low - 1e-9 <= value <= high + 1e-9:  # a continuous joint's limits are infinite
                raise ModelError(f"start: q{j + 1} = {value:g} deg is outside joint {j + 1}'s limits [{low:g}, {high:g}] deg "
                                 "(start is in degrees)")

    def priority(self) -> PrioritySettings:
        """The damping and feedback in SI units."""
        return PrioritySettings(orientation_eps=self.orientation_eps, orientation_damping=self.orientation_damping,
                                position_eps=self.position_eps * 1e-3, position_damping=self.position_damping * 1e-3,
                                gain=self.gain * 1e3)

    def limits(self, robot: RobotModel) -> tuple[np.ndarray, np.ndarray, str]:
        """Joint speed (rad/s) and acceleration (rad/s^2) limits ``(N,)``, and where they come from."""
        if self.joint_speed:
            speed, source_v = np.array(self.joint_speed) * DEG, "option joint_speed"
        elif robot.velocity_limits is not None:
            speed, source_v = robot.velocity_limits.numpy().astype(np.float64), "robot file"
        elif robot.dof == len(KR6_SPEED_LIMITS_DEG_S):
            speed, source_v = np.array(KR6_SPEED_LIMITS_DEG_S) * DEG, "KR6-like defaults"
        else:
            raise ModelError(f"robot '{robot.name}' gives no joint speed limits; set joint_speed=[...] (deg/s)")
        if self.joint_accel:
            accel, source_a = np.array(self.joint_accel) * DEG, "option joint_accel"
        elif robot.acceleration_limits is not None:
            accel, source_a = robot.acceleration_limits.numpy().astype(np.float64), "robot file"
        else:
            accel, source_a = np.full(robot.dof, DEFAULT_JOINT_ACCEL_DEG_S2 * DEG), "default 3000 deg/s^2"
        return speed, accel, f"speeds: {source_v}; accelerations: {source_a}"


@dataclass(frozen=True)
class PlannedMotion:
    """A sampled joint trajectory and what it was planned from (SI units).

    Attributes:
        t: ``(K,)`` sample times, s (``k dt``).
        q: ``(K, N)`` joints, rad.
        s: ``(K,)`` path parameter at each sample, m.
        targets: ``(K, 4, 4)`` desired TCP poses at the samples, base frame.
        segment: ``(K,)`` waypoint segment of each sample (0 = first to second waypoint).
        sigma_position / sigma_orientation: ``(K,)`` smallest singular values of the tasks
            (m/rad, rad/rad) at the samples (from the geometric grid).
        law: the time law, after stretching.
        joint_speed / joint_accel: ``(N,)`` limits used, rad/s, rad/s^2; ``limit_source`` says whence.
        q_first: ``(N,)`` joints solved at the first waypoint; ``start`` the given start joints.
        stretch: factor by which time was stretched after the time law (>= 1).
    """

    t: np.ndarray
    q: np.ndarray
    s: np.ndarray
    targets: np.ndarray
    segment: np.ndarray
    sigma_position: np.ndarray
    sigma_orientation: np.ndarray
    law: TimeLaw
    joint_speed: np.ndarray
    joint_accel: np.ndarray
    limit_source: str
    q_first: np.ndarray
    start: np.ndarray
    stretch: float


def solve_first(kin: TcpKinematics, target: torch.Tensor, q0: torch.Tensor, settings: PrioritySettings,
                iterations: int = 200) -> torch.Tensor:
    """Joints at pose ``target`` from ``q0`` by full-error position-first steps (damped near singularities)."""
    q = q0.clone()
    for _ in range(iterations):
        pose, jac = kin(q)
        dp = target[:3, 3] - pose[:3, 3]
        dw = tf.so3_log(target[:3, :3] @ pose[:3, :3].T)
        if float(dp.norm()) < 1e-12 and float(dw.norm()) < 1e-11:
            break
        q = q + priority_step(jac, dp, dw, settings).dq
    return q


def joint_rates(q: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Speeds ``(K-1, N)`` and accelerations ``(K, N)`` of samples ``q`` ``(K, N)`` by finite differences.

    The robot rests before the first and after the last sample, so the accelerations include
    the start from rest and the stop: ``(q[k+1] - 2 q[k] + q[k-1]) / dt^2`` with ``q[-1] = q[0]``
    and ``q[K] = q[K-1]``.
    """
    padded = np.concatenate([q[:1], q, q[-1:]], 0)
    return np.diff(q, axis=0) / dt, (padded[2:] - 2.0 * padded[1:-1] + padded[:-2]) / dt**2


def plan_motion(kin: TcpKinematics, robot: RobotModel, waypoints: torch.Tensor, options: PlanOptions) -> PlannedMotion:
    """Joint trajectory along ``waypoints`` ``(M, 4, 4)`` (base frame, m) for ``kin`` (module docstring)."""
    options.check(robot)
    settings = options.priority()
    speed_limit, accel_limit, source = options.limits(robot)
    dtype = torch.float64
    start = torch.tensor(options.start, dtype=dtype) * DEG
    path = WaypointPath(waypoints.to(dtype), options.speed * 1e-3, options.angular_speed * DEG)
    q_first = solve_first(kin, path.poses[0], start, settings)

    # 2. geometric pass per segment, 3. splines and time laws per segment
    from scipy.interpolate import CubicSpline

    splines, laws, grids, offset = [], [], [], 0.0
    q = q_first
    h_max = options.step * 1e-3
    points = [max(3, math.ceil((float(path.knots[i + 1]) - float(path.knots[i])) / h_max)) for i in range(len(path.ell))]
    if sum(points) > MAX_GRID_POINTS:
        raise ModelError(f"the path is {float(path.knots[-1]) * 1e3:.6g} mm long: {sum(points)} grid points of step="
                         f"{options.step:g} mm, more than {MAX_GRID_POINTS}; give a larger step (or a shorter path)")
    for i in range(len(path.ell)):
        s0, s1 = float(path.knots[i]), float(path.knots[i + 1])
        n = points[i]
        s = torch.linspace(s0, s1, n + 1, dtype=dtype)
        sol = follow_geometric(kin, path.poses_at, s, q, settings)
        q = sol.q[-1]
        s_np, q_np = s.numpy(), sol.q.numpy()
        spline = CubicSpline(s_np, q_np, axis=0)
        law = time_optimal(s_np, spline(s_np, 1), spline(s_np, 2), speed=options.speed * 1e-3,
                           path_accel=options.accel * 1e-3, joint_speed=speed_limit, joint_accel=accel_limit)
        splines.append(spline)
        laws.append(TimeLaw(law.s, law.s_dot, law.t + offset))
        grids.append(sol)
        offset += law.duration

    # 4. whole periods, samples, position correction; 5. measured limits
    dt = options.dt
    if offset / dt > MAX_SAMPLES:
        raise ModelError(f"the motion would take {offset:.1f} s, more than {MAX_SAMPLES} samples of {dt:g} s: the joint "
                         "limits admit almost no speed somewhere on the path (a singularity the path crosses?)")
    stretch = math.ceil(offset / dt - 1e-9) * dt / offset
    for _ in range(6):
        t, q_k, s_k, seg = _sample(laws, splines, stretch, dt)
        targets = path.poses_at(torch.from_numpy(s_k))
        q_k = correct_position(kin, torch.from_numpy(q_k), targets, settings).numpy()
        speed, accel = joint_rates(q_k, dt)
        ratio = max(float(np.max(np.abs(speed) / speed_limit)), math.sqrt(float(np.max(np.abs(accel) / accel_limit))))
        if ratio <= 1.0 or ratio > 2.0:  # met; or not a grid effect (reported as measured, never hidden)
            break
        total = offset * stretch * ratio * 1.0005
        stretch = math.ceil(total / dt - 1e-9) * dt / offset
    s_grid = np.concatenate([g.s.numpy() for g in grids])
    sp = np.interp(s_k, s_grid, np.concatenate([g.sigma_position.numpy() for g in grids]))
    so = np.interp(s_k, s_grid, np.concatenate([g.sigma_orientation.numpy() for g in grids]))
    law_all = TimeLaw(np.concatenate([law.s for law in laws]), np.concatenate([law.s_dot for law in laws]) / stretch,
                      np.concatenate([law.t for law in laws]) * stretch)
    return PlannedMotion(t=t, q=q_k, s=s_k, targets=targets.numpy(), segment=seg, sigma_position=sp,
                         sigma_orientation=so, law=law_all, joint_speed=speed_limit, joint_accel=accel_limit,
                         limit_source=source, q_first=q_first.numpy(), start=start.numpy(), stretch=stretch)


def _sample(laws: list[TimeLaw], splines: list, stretch: float, dt: float):
    """Times, spline joints, path parameter and segment of every sample of the stretched laws."""
    end = laws[-1].t[-1] * stretch
    k = round(end / dt)
    t = np.arange(k + 1) * dt
    local = t / stretch  # time of the unstretched laws
    bounds = np.array([law.t[0] for law in laws] + [laws[-1].t[-1]])
    seg = np.clip(np.searchsorted(bounds, local, side="right") - 1, 0, len(laws) - 1)
    s = np.empty_like(t)
    q = np.empty((len(t), splines[0].c.shape[-1]))
    for i, (law, spline) in enumerate(zip(laws, splines)):
        mask = seg == i
        if not mask.any():
            continue
        s[mask] = TimeLaw(law.s, law.s_dot, law.t - law.t[0]).sample(local[mask] - law.t[0])
        q[mask] = spline(s[mask])
    return t, q, s, seg


def between_samples_error_mm(kin: TcpKinematics, q: torch.Tensor, targets: torch.Tensor) -> np.ndarray:
    """``(K-1,)`` mm: how far the TCP passes from the path halfway between two samples when a
    controller interpolates the joints linearly: the distance of the TCP at the joints' midpoint from
    the straight piece between the two samples' targets (the path between waypoints is straight)."""
    if len(q) < 2:
        return np.zeros(0)
    mid = kin.pose(0.5 * (q[1:] + q[:-1]))[:, :3, 3]
    a, b = targets[:-1, :3, 3], targets[1:, :3, 3]
    chord = b - a
    length2 = (chord * chord).sum(-1, keepdim=True)
    lam = torch.where(length2 > 0, ((mid - a) * chord).sum(-1, keepdim=True) / length2.clamp_min(1e-300), 0.0).clamp(0.0, 1.0)
    return ((mid - (a + lam * chord)).norm(dim=-1) * 1e3).numpy()


def measure(kin: TcpKinematics, planned: PlannedMotion, settings: PrioritySettings) -> dict:
    """Figures of a planned motion (mm, deg, s), measured on its samples by forward kinematics and
    finite differences: what a controller interpolating the joints every ``dt`` would get (the path
    error also halfway between samples, :func:`between_samples_error_mm`).

    The singular neighbourhoods are the samples where a task's smallest singular value is below its
    ``eps``: there the orientation (``Jo'``: wrist singularities, and shoulder or stretched-elbow
    ones, where the wrist can still place the TCP) or the position (``Jp``: the TCP at the edge of
    its reach) yields.
    """
    q = torch.from_numpy(planned.q)
    pose = kin.pose(q)
    targets = torch.from_numpy(planned.targets)
    position = (pose[:, :3, 3] - targets[:, :3, 3]).norm(dim=-1).numpy() * 1e3
    rotation = tf.rotation_angle(targets[:, :3, :3] @ pose[:, :3, :3].transpose(-1, -2)).numpy() / DEG
    dt = float(planned.t[1] - planned.t[0]) if len(planned.t) > 1 else 0.0
    speed, accel = joint_rates(planned.q, dt)
    wrist = planned.sigma_orientation < settings.orientation_eps
    arm = planned.sigma_position < settings.position_eps
    singular = wrist | arm
    regular = ~singular

    between = between_samples_error_mm(kin, q, targets)

    def peak(values: np.ndarray, mask: np.ndarray | None = None) -> float:
        chosen = values if mask is None else values[mask]
        return float(np.max(chosen)) if chosen.size else float("nan")

    return {
        "n_samples": len(planned.t),
        "duration_s": float(planned.t[-1]),
        "path_error_max_mm": peak(position),
        "path_error_rms_mm": float(np.sqrt(np.mean(position**2))),
        "start_error_mm": float(position[0]),
        "end_error_mm": float(position[-1]),
        "path_error_between_samples_max_mm": float(between.max()) if between.size else 0.0,
        "path_error_regular_max_mm": peak(position, regular),
        "path_error_singular_max_mm": peak(position, singular),
        "orientation_deviation_max_deg": peak(rotation),
        "orientation_deviation_regular_max_deg": peak(rotation, regular),
        "orientation_deviation_singular_max_deg": peak(rotation, singular),
        "samples_orientation_yielding": int(wrist.sum()),
        "samples_position_yielding": int(arm.sum()),
        "joint_speed_max_deg_s": (np.abs(speed).max(0) / DEG).tolist(),
        "joint_speed_limit_deg_s": (planned.joint_speed / DEG).tolist(),
        "joint_accel_max_deg_s2": (np.abs(accel).max(0) / DEG).tolist(),
        "joint_accel_limit_deg_s2": (planned.joint_accel / DEG).tolist(),
        "tcp_speed_max_mm_s": float(np.max(np.linalg.norm(np.diff(pose[:, :3, 3].numpy(), axis=0), axis=-1)) / dt * 1e3)
        if dt else 0.0,
        "time_stretch": planned.stretch,
        "first_waypoint_from_start_deg": float(np.max(np.abs(planned.q_first - planned.start)) / DEG),
        "sigma_orientation_min": float(planned.sigma_orientation.min()),
        "sigma_position_min_mm": float(planned.sigma_position.min() * 1e3),
        "position_error_mm": position,
        "between_samples_error_mm": between,
        "orientation_deviation_deg": rotation,
        "joint_speed_deg_s": speed / DEG,
        "joint_accel_deg_s2": accel / DEG,
    }
