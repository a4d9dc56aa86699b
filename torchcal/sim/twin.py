"""The digital twin: a "true" robot with known errors, measured by a simulated laser tracker.

Truth = nominal robot + random geometric errors of every kind the error layer has (MDH rows,
Hayati beta on parallel axes, instrument frame, tool offset), optionally plus non-geometric
errors the geometric model cannot express:

* gravity-induced joint compliance: each joint deflects by ``tau_j / k_j`` where ``tau_j`` is
  the gravity torque of point masses on the links about joint ``j``'s axis;
* periodic gear (transmission) errors: ``sum_n A_jn sin(n q_j + phi_jn)`` per joint, harmonics
  ``n = 1 .. gear_orders`` (amplitude of order ``n``: uniform up to ``gear_amplitude_deg / n``);
* nonlinear compliance (``compliance_cubic``): the joint's stiffness changes with the load,
  ``dq_j = (tau_j / k_j) (1 + compliance_cubic (tau_j / tau_ref_j)^2)`` with ``tau_ref_j`` the
  largest gravity torque of joint ``j`` over a fixed sample of the workspace (a positive value
  softens the joint, a negative one stiffens it).

Measurements add robot repeatability (isotropic Gaussian, per axis) and tracker noise (per axis).
The noise floor of a 3-D position RMS is ``sqrt(3 (sigma_tracker^2 + sigma_repeat^2))``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import torch

from torchcal.data.measurements import Measurements
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.joint_jacobian import joint_frames
from torchcal.kinematics.robot import RobotModel, default_robot_path, load_robot
from torchcal.sim.twin_config import TwinConfig


@dataclass
class Twin:
    """A true robot: nominal model, true parameters and non-geometric error settings."""

    config: TwinConfig
    robot: RobotModel
    model: ErrorModel
    x_true: torch.Tensor
    gear_amplitude: torch.Tensor
    gear_phase: torch.Tensor
    torque_reference: torch.Tensor | None = None

    @classmethod
    def create(cls, config: TwinConfig) -> Twin:
        robot = load_robot(config.robot or default_robot_path())
        limits = robot.joint_limits.to(torch.float64)
        config.check_margin([math.degrees(float(hi - lo)) for lo, hi in limits.tolist() if math.isfinite(hi - lo)])
        gen = torch.Generator().manual_seed(config.seed)
        model = ErrorModel(robot)
        layout = model.layout
        x = model.nominal_vector()
        is_angle = layout.is_angle()
        sigma = torch.where(is_angle, math.radians(config.angle_error_deg), config.length_error_mm * 1e-3)
        noise = torch.randn(layout.size, generator=gen, dtype=torch.float64) * sigma
        table = torch.zeros(layout.size, dtype=torch.bool)
        table[layout.table_slice] = True
        # Every MDH parameter is perturbed, beta only where the Hayati rule makes it meaningful.
        for i in range(1, robot.dof + 1):
            if i not in model.parallel_joints:
                table[layout.index(f"beta{i}")] = False
        x = x + noise * table
        tool = x[layout.tool_slice]
        tool[:3] = tool[:3] + torch.randn(3, generator=gen, dtype=torch.float64) * config.tool_error_mm * 1e-3
        # Instrument: a tracker a few metres away, arbitrarily rotated.
        direction = torch.randn(3, generator=gen, dtype=torch.float64)
        direction[2] = direction[2].abs() * 0.2
        direction = direction / direction.norm()
        base = x[layout.base_slice]
        base[:3] = direction * config.instrument_distance_mm * 1e-3
        base[3:] = torch.randn(3, generator=gen, dtype=torch.float64) * 0.8
        # the first two orders are drawn first, as before there were more: a twin of two orders stays the same
        orders = max(config.gear_orders, 2)
        amplitude = torch.rand(robot.dof, 2, generator=gen, dtype=torch.float64) * math.radians(config.gear_amplitude_deg)
        amplitude[:, 1] *= 0.5
        phase = torch.rand(robot.dof, 2, generator=gen, dtype=torch.float64) * 2 * math.pi
        if orders > 2:
            more = torch.rand(robot.dof, orders - 2, generator=gen, dtype=torch.float64) * math.radians(config.gear_amplitude_deg)
            amplitude = torch.cat([amplitude, more / torch.arange(3, orders + 1, dtype=torch.float64)], 1)
            phase = torch.cat([phase, torch.rand(robot.dof, orders - 2, generator=gen, dtype=torch.float64) * 2 * math.pi], 1)
        amplitude, phase = amplitude[:, : config.gear_orders], phase[:, : config.gear_orders]
        twin = cls(config, robot, model, x, amplitude, phase)
        if config.compliance_cubic != 0.0:
            sample = robot.sample_joints(2000, torch.Generator().manual_seed(config.seed + 104729))
            twin.torque_reference = twin.gravity_torque(sample).abs().amax(0).clamp_min(1e-9)
        return twin

    def T_instrument_base(self) -> torch.Tensor:
        return self.model.instrument_from_base(self.x_true)

    def joint_deviation(self, q: torch.Tensor) -> torch.Tensor:
        """Non-geometric joint deviations ``(B, N)`` rad: gear errors plus gravity compliance."""
        dq = torch.zeros_like(q)
        if self.config.gear:
            dq = dq + self.gear_deviation(q)
        if self.config.gravity:
            dq = dq + self.gravity_deflection(q)
        return dq

    def gear_deviation(self, q: torch.Tensor) -> torch.Tensor:
        """Gear (transmission) errors ``(B, N)`` rad at commanded joints ``q`` ``(B, N)`` rad."""
        harmonic = torch.arange(1, self.gear_amplitude.shape[1] + 1, dtype=q.dtype)
        return (self.gear_amplitude * torch.sin(q.unsqueeze(-1) * harmonic + self.gear_phase)).sum(-1)

    def gravity_deflection(self, q: torch.Tensor) -> torch.Tensor:
        """Joint deflection (rad) from gravity on point link masses, ``base`` z up: ``tau_j / k_j``,
        times ``1 + compliance_cubic (tau_j / tau_ref_j)^2`` for a nonlinear compliance."""
        n = self.robot.dof
        values = list(self.config.joint_stiffness_nm_per_rad[:n])
        values += values[-1:] * (n - len(values))  # a robot with more joints: the last (wrist) value again
        stiffness = torch.tensor(values, dtype=q.dtype)
        tau = self.gravity_torque(q)
        if self.torque_reference is None:
            return tau / stiffness
        return tau / stiffness * (1.0 + self.config.compliance_cubic * (tau / self.torque_reference.to(q)) ** 2)

    def gravity_torque(self, q: torch.Tensor) -> torch.Tensor:
        """Gravity torque ``(B, N)`` (N m) of the point link masses about each joint, ``base`` z up."""
        base_model = ErrorModel(self.robot)
        x = self.x_true.clone()
        x[self.model.layout.base_slice] = 0.0
        axes, origins = joint_frames(base_model, q, x)
        tcp = base_model.tcp_position(q, x)
        n = self.robot.dof
        # Masses: middle of link 2 (between joints 2 and 3), middle of link 3 (joints 3 to 5), wrist.
        points = torch.stack(
            [0.5 * (origins[:, 1] + origins[:, 2]), 0.5 * (origins[:, 2] + origins[:, min(4, n - 1)]), tcp], 1
        )
        masses = torch.tensor(self.config.link_masses_kg, dtype=q.dtype)
        gravity = torch.tensor([0.0, 0.0, -9.81], dtype=q.dtype)
        tau = torch.zeros_like(q)
        for j in range(n):
            lever = points - origins[:, j : j + 1]
            # a mass loads joint j only if it sits beyond it: link 2 beyond joints 1-2,
            # link 3 beyond joints 1-3, the wrist/payload beyond every joint
            beyond = torch.tensor([j < last for last in (2, 3, n)], dtype=q.dtype)
            force = ((masses * beyond).unsqueeze(-1) * gravity).expand_as(lever)
            moment = torch.linalg.cross(lever, force, dim=-1).sum(1)
            tau[:, j] = (moment * axes[:, j]).sum(-1)
        return tau

    def true_positions(self, q: torch.Tensor) -> torch.Tensor:
        """Noise-free TCP positions ``(B, 3)`` in the instrument frame, m."""
        return self.model.tcp_position(q + self.joint_deviation(q), self.x_true)

    def true_tcp_positions(self, q: torch.Tensor, T_flange_tcp: torch.Tensor) -> torch.Tensor:
        """Noise-free positions ``(B, 3)`` (instrument frame, m) of a production TCP ``T_flange_tcp``
        ``(4, 4)`` given in the flange frame (the flange itself: the identity), not the measured point."""
        T = self.T_instrument_base() @ self.model.base_flange_pose(q + self.joint_deviation(q), self.x_true)
        return (T @ T_flange_tcp.to(T))[..., :3, 3]

    def measure(self, q: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Noisy tracker measurement of the TCP at commanded joints ``q``."""
        clean = self.true_positions(q)
        c = self.config
        noise = torch.randn(clean.shape, generator=generator, dtype=clean.dtype) * math.hypot(c.tracker_sigma_mm, c.repeatability_mm) * 1e-3
        return clean + noise

    def sample(self, n: int, generator: torch.Generator) -> Measurements:
        q = self.robot.sample_joints(n, generator, margin=math.radians(self.config.margin_deg))
        return Measurements(q=q, position=self.measure(q, generator))

    def changed(self, **deltas: float) -> Twin:
        """The same twin with true parameters moved by ``deltas`` (layout names, SI units: m, rad),
        as after a tool swap, a re-mastered joint or a bent link."""
        x = self.x_true.clone()
        for name, delta in deltas.items():
            x[self.model.layout.index(name)] += delta
        return replace(self, x_true=x)

    def truth_dict(self) -> dict:
        names = self.model.layout.names
        scale = self.model.layout.unit_scale()
        values = (self.x_true * scale).tolist()
        t = self.T_instrument_base()
        return {
            "robot": self.robot.name,
            "units": {"lengths": "mm", "angles": "deg"},
            "parameters": {n: v for n, v in zip(names, values) if not n.startswith("base_")},
            "T_instrument_base": {
                "rotation": t[:3, :3].tolist(),
                "translation_mm": (t[:3, 3] * 1e3).tolist(),
            },
            "tool_mm": (self.x_true[self.model.layout.tool_slice][:3] * 1e3).tolist(),
            # a URDF robot's fixed transforms, without which the table and tool do not give the TCP
            "T_base_0": {"rotation": self.robot.T_base_0[:3, :3].tolist(),
                         "translation_mm": (self.robot.T_base_0[:3, 3] * 1e3).tolist()},
            "T_n_flange": {"rotation": self.robot.T_n_flange[:3, :3].tolist(),
                           "translation_mm": (self.robot.T_n_flange[:3, 3] * 1e3).tolist()},
            "tcp_model": "T_instrument_base @ T_base_0 @ MDH(table, q) @ T_n_flange @ [tool_mm; 1]",
            "noise_floor_rms_mm": self.config.noise_floor_rms_mm,
            "non_geometric": {
                "gravity": self.config.gravity,
                "gear": self.config.gear,
                "gear_amplitude_deg": (self.gear_amplitude * 180 / math.pi).tolist(),
                "gear_phase_rad": self.gear_phase.tolist(),
                "gear_model": "dq_j = sum_n A_jn sin(n q_j + phi_jn), n = 1 .. gear_orders (rows: joints)",
                "compliance_cubic": self.config.compliance_cubic,
                "torque_reference_nm": None if self.torque_reference is None else self.torque_reference.tolist(),
                "compliance_model": "dq_j = tau_j / k_j * (1 + compliance_cubic * (tau_j / torque_reference_j)^2)",
            },
            "config": asdict(self.config),
        }
