"""Which flange motions to command to calibrate a profile sensor on a plane target.

Rules (derived in :mod:`torchcal.instruments.profile.closed_form`; see docs/profile.md):

* **Plane orientations.** The closed form needs >= 3 placements (or flange orientations) whose
  normals, seen from the flange, are not coplanar. The planner views each placement obliquely,
  from a view direction tilted by ``view_tilt_deg`` away from its normal about an axis that
  turns by ``360 / n_planes`` per placement (unless view directions are given).
* **Translations.** At the reference orientation of each placement: >= 3 pure translations along
  the sensor axes x, y, z (then diagonals), so the flange positions span 3-D. Their size is a
  share of the working range (``translation_share`` of the u range for x and y, of the w range
  for z): the normal estimate's error scales as ``sigma_w / (translation sqrt(points))``.
* **Rotations.** About the sensor x, y and z axes through the centre of view (the point seen
  at ``u = 0``, mid-depth), so the line stays in range; at least two non-parallel axes are
  needed for ``t``.
* **Limits.** Each scan must be reachable within the joint limits (batched damped
  least-squares IK from the placement's reference solution) and keep the predicted line inside
  the ``u``/``w`` window over ``min_visible`` of the u range; a motion that fails is halved (up
  to 4 times) before the plan is rejected with a clear message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.core.errors import TorchcalError
from torchcal.instruments.profile.model import orthogonal_basis
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import solve_ik
from torchcal.kinematics.robot import RobotModel


@dataclass(frozen=True)
class SensorRange:
    """Working window of the sensor in its laser plane, m: ``u`` along the line, ``w`` depth."""

    u_min: float = -0.025
    u_max: float = 0.025
    w_min: float = 0.080
    w_max: float = 0.160

    @property
    def w_mid(self) -> float:
        return 0.5 * (self.w_min + self.w_max)


@dataclass(frozen=True)
class PlanConfig:
    """Motion design settings.

    Attributes:
        n_translations: pure translations per placement (>= 3; x, y, z then diagonals).
        n_rotations: rotations per placement (>= 2 axes needed; x, y, z then diagonals).
        translation_share: translation size as a share of the u (x, y) or w (z) range.
        rotation_deg: rotation angle about each axis.
        view_tilt_deg: obliquity of the view to the plane normal (default view directions).
        min_visible: share of the u range the predicted line must cover inside the window.
        ik_starts: random IK starts for each placement's reference pose.
    """

    n_translations: int = 3
    n_rotations: int = 3
    translation_share: float = 0.3
    rotation_deg: float = 10.0
    view_tilt_deg: float = 20.0
    min_visible: float = 0.6
    ik_starts: int = 64


@dataclass
class ProfilePlan:
    """Planned scans, in command order.

    Attributes:
        q: ``(S, N)`` joints, rad.
        T_base_flange: ``(S, 4, 4)`` nominal flange poses.
        plane: ``(S,)`` placement index.
        kinds: ``"reference" | "translation" | "rotation"`` per scan.
        motions: per scan, the commanded offset from the reference in the sensor frame:
            translation vector (m) or rotation vector (rad), zeros for the reference.
    """

    q: torch.Tensor
    T_base_flange: torch.Tensor
    plane: torch.Tensor
    kinds: list[str]
    motions: torch.Tensor


def _directions(count: int, dtype) -> torch.Tensor:
    """Sensor-frame unit axes: x, y, z, then alternating diagonals."""
    base = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [1, -1, 1], [-1, 1, 1], [1, 1, -1]]
    rows = [base[k % len(base)] for k in range(count)]
    d = torch.tensor(rows, dtype=dtype)
    sign = torch.tensor([1.0 if (k // len(base)) % 2 == 0 else -1.0 for k in range(count)], dtype=dtype)
    return d / d.norm(dim=-1, keepdim=True) * sign.unsqueeze(-1)


def sensor_pose_looking_at(point: torch.Tensor, view: torch.Tensor, w_mid: float) -> torch.Tensor:
    """``T_base_sensor`` ``(4, 4)`` with z along ``view`` and ``point`` at depth ``w_mid`` on its axis."""
    z = view / view.norm()
    x = orthogonal_basis(z)[0]
    return tf.homogeneous(torch.stack([x, torch.linalg.cross(z, x), z], -1), point - w_mid * z)


def default_view_directions(normals: torch.Tensor, tilt_deg: float) -> torch.Tensor:
    """View directions ``(P, 3)``: ``-n`` tilted by ``tilt_deg`` about an axis turning per placement."""
    out = []
    for k, n in enumerate(normals):
        b = orthogonal_basis(n)
        phi = 2 * math.pi * k / len(normals)
        axis = math.cos(phi) * b[0] + math.sin(phi) * b[1]
        out.append(-(tf.so3_exp(axis * math.radians(tilt_deg)) @ n))
    return torch.stack(out)


def visible_share(T_base_sensor: torch.Tensor, normal: torch.Tensor, point: torch.Tensor, window: SensorRange) -> torch.Tensor:
    """Share ``(B,)`` of the u range whose line point lies inside the w window."""
    k = T_base_sensor[..., :3, :3].transpose(-1, -2) @ normal  # normal in the sensor frame
    d = (point - T_base_sensor[..., :3, 3]) @ normal
    u = torch.linspace(window.u_min, window.u_max, 101, dtype=normal.dtype)
    kz = k[..., 2:3]
    w = (d.unsqueeze(-1) - k[..., 0:1] * u) / torch.where(kz.abs() < 1e-9, torch.full_like(kz, 1e-9), kz)
    inside = (w >= window.w_min) & (w <= window.w_max)
    return inside.double().mean(-1)


def _reach(model: ErrorModel, x: torch.Tensor, targets: torch.Tensor, q0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """IK of flange poses ``(B, 4, 4)`` from ``q0`` ``(B, N)``: joints and whether reached within limits."""
    coarse = solve_ik(model, x, targets, q0, damping=0.05, max_iterations=60)
    fine = solve_ik(model, x, targets, coarse.q, max_iterations=30)
    # revolute joints: a solution 2 pi away is the same pose, so wrap towards the middle of the range
    mid = model.robot.turn_limits.to(fine.q).mean(-1)
    q = fine.q - 2 * math.pi * torch.round((fine.q - mid) / (2 * math.pi))
    ok = fine.converged & model.robot.within_limits(q)
    return q, ok


def plan_profile_scans(
    robot: RobotModel,
    plane_normals: torch.Tensor,
    plane_points: torch.Tensor,
    R_flange_sensor: torch.Tensor,
    t_flange_sensor: torch.Tensor,
    window: SensorRange = SensorRange(),
    config: PlanConfig = PlanConfig(),
    *,
    view_directions: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
) -> ProfilePlan:
    """Plan reference, translation and rotation scans for each placement of the target.

    Args:
        robot: nominal robot (joint limits, kinematics).
        plane_normals / plane_points: ``(P, 3)`` each, placements in ``base``, m.
        R_flange_sensor / t_flange_sensor: the design (approximate) sensor mounting, m.
        window: the sensor's working window.
        config: motion sizes and counts.
        view_directions: ``(P, 3)`` sensor z for each reference pose (default: oblique views).
        generator: random IK starts.

    Raises:
        TorchcalError: fewer than 3 translations or 2 rotations, or a scan that cannot be
            reached within the joint limits / seen inside the window even after shrinking.
    """
    if config.n_translations < 3:
        raise TorchcalError("a plan needs >= 3 pure translations per placement (non-coplanar, for the rotation)")
    if config.n_rotations < 2:
        raise TorchcalError("a plan needs rotations about >= 2 non-parallel axes (for the translation)")
    if plane_normals.shape[0] < 3:
        raise TorchcalError(
            "a plan needs >= 3 placements of the target: each is seen at one reference orientation, and the closed "
            "form needs 3 plane orientations whose normals (flange frame) are not coplanar"
        )
    dtype = torch.float64
    generator = generator or torch.Generator().manual_seed(0)
    normals = plane_normals.to(dtype) / plane_normals.to(dtype).norm(dim=-1, keepdim=True)
    views = default_view_directions(normals, config.view_tilt_deg) if view_directions is None else view_directions.to(dtype)
    T_fs = tf.homogeneous(R_flange_sensor.to(dtype), t_flange_sensor.to(dtype))
    T_sf = tf.invert(T_fs)
    model = ErrorModel(robot)
    x = model.nominal_vector()
    x[model.layout.tool_slice] = 0.0  # the IK target is the flange itself
    span_u, span_w = window.u_max - window.u_min, window.w_max - window.w_min
    translations = _directions(config.n_translations, dtype)
    translations = translations * torch.tensor([span_u, span_u, span_w], dtype=dtype) * config.translation_share
    rotations = _directions(config.n_rotations, dtype) * math.radians(config.rotation_deg)

    q_all, T_all, plane_all, kinds, motions = [], [], [], [], []
    for k in range(normals.shape[0]):
        T_ref = sensor_pose_looking_at(plane_points[k].to(dtype), views[k], window.w_mid)
        if float(visible_share(T_ref, normals[k], plane_points[k].to(dtype), window)) < config.min_visible:
            raise TorchcalError(f"placement {k}: the line at the reference view leaves the w window; lower view_tilt_deg or widen the window")
        target = (T_ref @ T_sf).expand(config.ik_starts, 4, 4)
        q0 = robot.sample_joints(config.ik_starts, generator, margin=math.radians(10))
        q_ref, ok = _reach(model, x, target, q0)
        if not bool(ok.any()):
            raise TorchcalError(f"placement {k}: the reference view is not reachable within the joint limits")
        lim = robot.joint_limits
        margin = torch.minimum(q_ref - lim[:, 0], lim[:, 1] - q_ref).min(-1).values
        q_ref = q_ref[torch.where(ok, margin, torch.full_like(margin, -1e9)).argmax()]
        q_all.append(q_ref)
        T_all.append(T_ref @ T_sf)
        plane_all.append(k)
        kinds.append("reference")
        motions.append(torch.zeros(3, dtype=dtype))
        centre = T_ref[:3, :3] @ torch.tensor([0.0, 0.0, window.w_mid], dtype=dtype) + T_ref[:3, 3]
        for kind, moves in (("translation", translations), ("rotation", rotations)):
            for move in moves:
                for _ in range(5):
                    if kind == "translation":
                        T_s = T_ref.clone()
                        T_s[:3, 3] = T_ref[:3, 3] + T_ref[:3, :3] @ move
                    else:
                        R_b = tf.so3_exp(T_ref[:3, :3] @ move)  # sensor-axis rotation, about the centre of view
                        T_s = tf.homogeneous(R_b @ T_ref[:3, :3], R_b @ (T_ref[:3, 3] - centre) + centre)
                    seen = float(visible_share(T_s, normals[k], plane_points[k].to(dtype), window)) >= config.min_visible
                    q, ok = _reach(model, x, (T_s @ T_sf).unsqueeze(0), q_ref.unsqueeze(0))
                    if seen and bool(ok[0]):
                        break
                    move = move * 0.5
                else:
                    raise TorchcalError(
                        f"placement {k}: a {kind} of the plan cannot be reached within the joint limits or keeps the "
                        "line outside the window even at 1/16 of its size; move the target or change the view"
                    )
                q_all.append(q[0])
                T_all.append(T_s @ T_sf)
                plane_all.append(k)
                kinds.append(kind)
                motions.append(move)
    return ProfilePlan(
        q=torch.stack(q_all),
        T_base_flange=torch.stack(T_all),
        plane=torch.tensor(plane_all),
        kinds=kinds,
        motions=torch.stack(motions),
    )
