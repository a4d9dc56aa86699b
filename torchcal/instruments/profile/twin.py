"""Digital twin of a flange-mounted line-laser profile sensor scanning a plane target.

The robot is the embedded twin robot (nominal kinematics, so the flange poses of the fit are
exact unless robot repeatability noise is switched on). The sensor is mounted at a design pose
(looking along the flange z, turned about it by a random angle, offset by tens of mm) plus a
mounting error of a few degrees and mm: the truth. The target is placed ``n_planes`` times,
tilted ``plane_tilt_deg`` from horizontal at spread azimuths; the motions come from
:func:`torchcal.instruments.profile.plan.plan_profile_scans` with the *design* mounting, as a real
cell would plan them. Each scan samples ``points_per_scan`` columns uniformly over the u range,
keeps those inside the w window and adds Gaussian depth noise (``noise_w_mm``) and optionally
u noise; robot repeatability perturbs each scan's true flange pose (translation and rotation).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.instruments.profile.data import ProfileData, write_profile_csv
from torchcal.instruments.profile.plan import (
    PlanConfig,
    ProfilePlan,
    SensorRange,
    plan_profile_scans,
)
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.robot import RobotModel, default_robot_path, load_robot, robot_to_yaml


@dataclass
class ProfileTwinConfig:
    """Settings of a profile twin case (contract units: mm, deg).

    Attributes:
        seed: seeds the mounting, the placements, the IK starts and the noise.
        n_planes: placements of the target (>= 3).
        points_per_scan: profile columns sampled over the u range (those in the window are kept).
        noise_w_mm / noise_u_mm: Gaussian noise on depth and on position along the line.
        repeatability_mm / repeatability_deg: per-scan random error of the true flange pose.
        u_min_mm / u_max_mm / w_min_mm / w_max_mm: working window of the sensor.
        mount_error_deg / mount_error_mm: 1-sigma of the truth's deviation from the design mount.
        plane_tilt_deg: tilt of each placement from horizontal.
        target_x_mm / target_y_mm / target_z_mm / target_spread_mm: where the placements are.
        n_translations / n_rotations / translation_share / rotation_deg: the motion plan.
        view_down: view every placement along base -z (the tilted planes give the orientations);
            otherwise the planner's oblique default views.
    """

    seed: int = 0
    n_planes: int = 3
    points_per_scan: int = 800
    noise_w_mm: float = 0.015
    noise_u_mm: float = 0.0
    repeatability_mm: float = 0.0
    repeatability_deg: float = 0.0
    u_min_mm: float = -25.0
    u_max_mm: float = 25.0
    w_min_mm: float = 80.0
    w_max_mm: float = 160.0
    mount_error_deg: float = 2.0
    mount_error_mm: float = 2.0
    plane_tilt_deg: float = 35.0
    target_x_mm: float = 500.0
    target_y_mm: float = 0.0
    target_z_mm: float = 300.0
    target_spread_mm: float = 100.0
    n_translations: int = 4
    n_rotations: int = 6
    translation_share: float = 0.3
    rotation_deg: float = 15.0
    view_down: bool = True

    @property
    def window(self) -> SensorRange:
        return SensorRange(self.u_min_mm * 1e-3, self.u_max_mm * 1e-3, self.w_min_mm * 1e-3, self.w_max_mm * 1e-3)


class ProfileTwin:
    """True sensor mounting, target placements and the planned scans of one twin case.

    Args:
        config: twin settings (default: ``ProfileTwinConfig()``).
        robot: nominal robot (default: the embedded twin-kr6).
    """

    def __init__(self, config: ProfileTwinConfig | None = None, *, robot: RobotModel | None = None) -> None:
        config = config if config is not None else ProfileTwinConfig()
        if config.n_planes < 3:
            raise ValueError("the profile twin needs n_planes >= 3")
        self.config = config
        self.robot = robot if robot is not None else load_robot(default_robot_path())
        gen = torch.Generator().manual_seed(config.seed)
        dt = torch.float64
        psi = float(torch.rand(1, generator=gen, dtype=dt)) * 2 * math.pi
        self.R_design = tf.rot_z(torch.tensor(psi, dtype=dt))
        self.t_design = torch.cat(
            [torch.randn(2, generator=gen, dtype=dt) * 0.03, 0.09 + 0.04 * torch.rand(1, generator=gen, dtype=dt)]
        )
        self.R_true = tf.so3_exp(torch.randn(3, generator=gen, dtype=dt) * math.radians(config.mount_error_deg)) @ self.R_design
        self.t_true = self.t_design + torch.randn(3, generator=gen, dtype=dt) * config.mount_error_mm * 1e-3
        # Placements: tilted planes at spread azimuths around the target area.
        azimuth0 = float(torch.rand(1, generator=gen, dtype=dt)) * 2 * math.pi
        normals, points = [], []
        for k in range(config.n_planes):
            phi = azimuth0 + 2 * math.pi * k / config.n_planes
            tilt = math.radians(config.plane_tilt_deg)
            normals.append(torch.tensor([math.sin(tilt) * math.cos(phi), math.sin(tilt) * math.sin(phi), math.cos(tilt)], dtype=dt))
            r = config.target_spread_mm * 1e-3 * math.sqrt(float(torch.rand(1, generator=gen, dtype=dt)))
            angle = float(torch.rand(1, generator=gen, dtype=dt)) * 2 * math.pi
            points.append(
                torch.tensor([config.target_x_mm, config.target_y_mm, config.target_z_mm], dtype=dt) * 1e-3
                + r * torch.tensor([math.cos(angle), math.sin(angle), 0.0], dtype=dt)
            )
        self.normals = torch.stack(normals)
        self.points = torch.stack(points)
        self.offsets = (self.normals * self.points).sum(-1)
        views = torch.tensor([0.0, 0.0, -1.0], dtype=dt).expand(config.n_planes, 3) if config.view_down else None
        plan_config = PlanConfig(
            n_translations=config.n_translations,
            n_rotations=config.n_rotations,
            translation_share=config.translation_share,
            rotation_deg=config.rotation_deg,
        )
        self.plan: ProfilePlan = plan_profile_scans(
            self.robot, self.normals, self.points, self.R_design, self.t_design, config.window, plan_config,
            view_directions=views, generator=gen,
        )
        self._noise_seed = config.seed + 7919

    def true_flange_poses(self, generator: torch.Generator) -> torch.Tensor:
        """``(S, 4, 4)`` true flange poses of the plan: nominal FK with repeatability errors."""
        c = self.config
        T = self.robot.flange_pose(self.plan.q)
        n = T.shape[0]
        dt = T.dtype
        if c.repeatability_deg > 0:
            T = T.clone()
            T[:, :3, :3] = tf.so3_exp(torch.randn(n, 3, generator=generator, dtype=dt) * math.radians(c.repeatability_deg)) @ T[:, :3, :3]
        if c.repeatability_mm > 0:
            T = T.clone()
            T[:, :3, 3] = T[:, :3, 3] + torch.randn(n, 3, generator=generator, dtype=dt) * c.repeatability_mm * 1e-3
        return T

    def scan(self) -> ProfileData:
        """Noisy profile points of every planned scan (SI), labelled scan 0.. and plane 0.."""
        c = self.config
        gen = torch.Generator().manual_seed(self._noise_seed)
        T_bf = self.true_flange_poses(gen)
        T_bs = T_bf @ tf.homogeneous(self.R_true, self.t_true)
        n = self.normals[self.plan.plane]
        k = (T_bs[:, :3, :3].transpose(-1, -2) @ n.unsqueeze(-1)).squeeze(-1)  # normal, sensor frame
        d = self.offsets[self.plan.plane] - (n * T_bs[:, :3, 3]).sum(-1)
        u = torch.linspace(c.u_min_mm, c.u_max_mm, c.points_per_scan, dtype=torch.float64) * 1e-3
        w = (d.unsqueeze(-1) - k[:, :1] * u) / k[:, 2:3]
        inside = (w >= c.w_min_mm * 1e-3) & (w <= c.w_max_mm * 1e-3)
        scan_idx, col = inside.nonzero(as_tuple=True)
        uu = u[col] + torch.randn(col.shape[0], generator=gen, dtype=torch.float64) * c.noise_u_mm * 1e-3
        ww = w[scan_idx, col] + torch.randn(col.shape[0], generator=gen, dtype=torch.float64) * c.noise_w_mm * 1e-3
        return ProfileData(
            q=self.plan.q,
            plane=self.plan.plane,
            point_scan=scan_idx,
            uw=torch.stack([uu, ww], -1),
            scan_labels=tuple(str(j) for j in range(self.plan.q.shape[0])),
            plane_labels=tuple(str(k) for k in range(c.n_planes)),
        )

    def truth_dict(self) -> dict:
        """Known truth, JSON-ready (mm, deg)."""
        return {
            "robot": self.robot.name,
            "units": {"lengths": "mm", "angles": "deg"},
            "R_flange_sensor": self.R_true.tolist(),
            "t_flange_sensor_mm": (self.t_true * 1e3).tolist(),
            "design": {"R_flange_sensor": self.R_design.tolist(), "t_flange_sensor_mm": (self.t_design * 1e3).tolist()},
            "planes": [
                {"plane": k, "normal": self.normals[k].tolist(), "offset_mm": float(self.offsets[k]) * 1e3,
                 "point_mm": (self.points[k] * 1e3).tolist()}
                for k in range(self.config.n_planes)
            ],
            "scans": {"kinds": self.plan.kinds, "plane": self.plan.plane.tolist()},
            "flange_poses": "nominal kinematics of robot.yaml" + (
                " with repeatability errors" if self.config.repeatability_mm or self.config.repeatability_deg else ""
            ),
            "config": asdict(self.config),
        }


def write_profile_case(out: str | Path, config: ProfileTwinConfig | None = None) -> dict[str, Path]:
    """Write ``robot.yaml``, ``profile.csv`` and ``truth.json`` of a profile twin case to ``out``."""
    out = Path(out)
    twin = ProfileTwin(config)
    paths = {name: out / name for name in ("robot.yaml", "profile.csv", "truth.json")}
    atomic_write_text(paths["robot.yaml"], robot_to_yaml(twin.robot))
    write_profile_csv(paths["profile.csv"], twin.scan())
    atomic_write_json(paths["truth.json"], twin.truth_dict())
    return paths
