"""The compensator and monitor graphs: plain ``torch.nn.Module`` s with a fixed op sequence.

Frames: everything is in the calibrated robot ``base`` frame; the instrument transform of the
calibration (``T_instrument_base``) is not part of either graph. Units: joints in rad, lengths
in m.

**What the compensator solves.** The controller believes the nominal model: for a nominal
command ``q_t`` it expects the tool at ``T_t = T_nom(q_t)`` (nominal ``flange_pose(q_t) @ tool``).
The calibrated model (geometry ``x`` plus the optional learned residual ``r(q)``, a TCP position
error in ``base``, m) says where the tool really goes. The corrected command ``q_c`` is the one
that puts the calibrated TCP on the believed target::

    p_cal(q_c) + r(q_c) = p_t,      R_cal(q_c) = R_t.

**Sign convention** (that of the compensation patents): the predicted error of a command is
``dT(q) = T_real(q) - T_nom(q)``, for positions ``dp(q) = p_cal(q) + r(q) - p_nom(q)`` (the
:class:`MonitorGraph` output). The compensated target is ``T_c = T_t - dT`` and the command is its
nominal inverse kinematics ``q_c = IK_nom(T_c)``. The patents evaluate ``dT`` once at ``q_t``;
solving the equations above is the fixed point of that rule with ``dT`` taken at ``q_c`` itself,
so that ``p_nom(q_c) = p_t - dp(q_c)`` holds exactly (tested).

**Iterations.** Damped Newton (damped least squares) from ``q_t``: with the transposed
geometric Jacobian ``J^T`` ``(N, 6)`` of the calibrated model, each step is
``J^T (J J^T + lambda^2 I)^-1 e`` with ``e = [p_t - p_cal - r, vee(R_t R_cal^T)]`` (the vee of the
skew part is ``sin(angle) axis``: it vanishes exactly where the rotation error does and needs no
``acos``). The 6x6 solve is onnxruntime's one-node ``Inverse`` by default, or an unrolled
Gauss-Jordan of standard operators (``solver="gauss_jordan"``; :mod:`torchcal.compensate.linalg`).
It runs in float64 in every variant: a float32 graph casts ``J`` and ``e`` up for the solve and the
step back down. In float32, ``J^T J`` loses the small singular values of a near-singular pose to
rounding (~1e-7 relative), so a float32 solve there returns steps of the wrong size or NaN; the
two casts cost two nodes. The damping follows the error, ``lambda^2 = c |e|^2 + lambda_0^2``
(``c = 10``, ``lambda_0 = 1e-5``; Sugihara's rule): large while the error is large, so a step near a singularity stays bounded,
and vanishing as the error does, so regular poses converge quadratically. The residual's own
Jacobian is left out of the step: a learned error of ~0.1 mm varies by ~1e-4 m/rad against
~1 m/rad for the arm, so it only slows the contraction by ~1e-4 per step.

Measured on the twin (``twin-kr6`` with 0.3 mm / 0.03 deg geometric errors, corrections of a few
mm and mrad; 10,000 poses uniform within the joint limits; ``scripts/bench_onnx.py`` writes the
table to ``docs/bench_onnx.md``), the median TCP residual after 1, 2, 3 steps is about
``8e-6``, ``3e-10``, ``3e-16`` m and the share of poses below 1 nm 0 %, 58 %, 88 %; a fourth
step adds 6 % of the poses for a third more time. Three steps are the default: float64 is then
at rounding level wherever the Jacobian's smallest singular value exceeds ~0.01, and float32 at
its own floor (~1e-7 m). The remaining ~12 % of uniform poses lie near a wrist, elbow or shoulder
singularity, where an exact 6-D correction would need joint moves of tenths of a radian for a
few mm; there the damped step gives a partial, bounded correction (largest joint step about
0.25 rad in 3 steps; residual up to ~2 mm, below the uncompensated ~3 mm in these measurements). Position-only
tasks or a working space away from singularities avoid that regime.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from torchcal.compensate.chain import ChainGraph, geometric_jacobian_t
from torchcal.compensate.deflection import DeflectionGraph
from torchcal.compensate.joint_error_graph import JointErrorGraph
from torchcal.compensate.linalg import gauss_jordan, ort_solve
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import RobotModel

DEFAULT_ITERATIONS = 3
DEFAULT_DAMPING_GAIN = 10.0
DEFAULT_DAMPING_FLOOR = 1e-5
SOLVERS = {"inverse": ort_solve, "gauss_jordan": gauss_jordan}
"""The 6x6 solve of a step: onnxruntime's ``Inverse`` node, or the portable unrolled elimination."""


def _end_transforms(robot: RobotModel, model: ErrorModel, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``T_N_tool`` ``(4, 4)`` of the nominal and of the calibrated model."""
    tool_nominal = torch.eye(4, dtype=torch.float64)
    tool_nominal[:3, 3] = robot.tool.to(torch.float64)
    x = x.detach().cpu().to(torch.float64)
    t_n_flange = robot.T_n_flange.to(torch.float64)
    return t_n_flange @ tool_nominal, t_n_flange @ model.flange_from_tool(x).cpu()


def _residual_copy(residual: nn.Module | None, dtype: torch.dtype, device) -> nn.Module | None:
    if residual is None:
        return None
    module = copy.deepcopy(residual).to(device=device, dtype=dtype)
    module.eval()
    for p in module.parameters():
        p.requires_grad_(False)
    return module


def stored_parts(stored) -> dict:
    """Keyword arguments of the graphs from a :class:`~torchcal.model_store.StoredModel`: its
    residual head and its joint-space errors (so that no constructor can drop either)."""
    residual = stored.residual.to_torch_module() if stored.residual is not None else None
    return {"residual": residual, "joint_errors": JointSpaceErrors.from_metadata(stored.metadata)}


def command_jacobian_t(pose: torch.Tensor, joint_frames: torch.Tensor, slope: torch.Tensor | None) -> torch.Tensor:
    """Transposed Jacobian ``(B, N, 6)`` of the TCP with respect to the *commanded* joints.

    The chain turns by ``q + dq(q)``: row ``j`` of the geometric Jacobian at that point times
    ``1 + d dq_j / d q_j`` (``slope``, the harmonics'; ``None``: no joint-space errors).
    """
    jac_t = geometric_jacobian_t(pose, joint_frames)
    return jac_t if slope is None else jac_t * (1.0 + slope).unsqueeze(-1)


class _TwoModels(nn.Module):
    """Nominal and calibrated chains of one robot (shared by both graphs).

    With joint-space errors (``joint_errors``, :class:`JointErrorGraph`) the calibrated chain turns
    by ``q + dq(q)``; without them every method reduces to the plain chains, node for node.
    """

    def __init__(self, model: ErrorModel, x: torch.Tensor, residual: nn.Module | None, dtype: torch.dtype, device,
                 joint_errors: JointSpaceErrors | None = None) -> None:
        super().__init__()
        robot = model.robot
        x = x.detach().cpu().to(torch.float64)
        end_nominal, end_calibrated = _end_transforms(robot, model, x)
        tables = torch.stack([robot.table.to(torch.float64), model.table(x).cpu()])
        t0 = robot.T_base_0.to(torch.float64)
        self.both = ChainGraph(tables, t0, torch.stack([end_nominal, end_calibrated]), dtype=dtype, device=device)
        self.calibrated = ChainGraph(tables[1:], t0, end_calibrated.unsqueeze(0), dtype=dtype, device=device)
        self.residual = _residual_copy(residual, dtype, device)
        self.n_joints = robot.dof
        self.joint_errors = None
        if joint_errors is not None and not joint_errors.empty:
            self.joint_errors = JointErrorGraph(joint_errors, robot.dof, dtype=dtype, device=device)
            self.nominal = ChainGraph(tables[:1], t0, end_nominal.unsqueeze(0), dtype=dtype, device=device)

    def nominal_and_calibrated(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Nominal TCP pose ``(B, 4, 4)`` at ``q``, the calibrated TCP pose and joint frames
        ``(B, N, 4, 4)`` at ``q + dq(q)``, and the joint errors' slope ``(B, N)`` (or ``None``); ``base``, m."""
        if self.joint_errors is None:
            poses, frames = self.both(q, with_frames=True)
            return poses[:, 0], poses[:, 1], frames[:, 1], None
        nominal, nominal_frames = self.nominal(q, with_frames=True)
        nominal = nominal[:, 0]
        dq, slope = self.joint_errors(q, nominal_frames[:, 0], nominal[:, :3, 3])
        pose, frames = self.calibrated(q + dq, with_frames=True)
        return nominal, pose[:, 0], frames[:, 0], slope

    def calibrated_at(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Calibrated TCP pose and joint frames at ``q + dq(q)``, and the slope (or ``None``)."""
        if self.joint_errors is not None and self.joint_errors.needs_frames:
            return self.nominal_and_calibrated(q)[1:]
        slope = None
        if self.joint_errors is not None:
            dq, slope = self.joint_errors(q)
            q = q + dq
        pose, frames = self.calibrated(q, with_frames=True)
        return pose[:, 0], frames[:, 0], slope

    def add_residual(self, p: torch.Tensor, q: torch.Tensor, sign: float = 1.0) -> torch.Tensor:
        """``p + sign * r(q)`` ``(B, 3)`` (m, ``base``); ``p`` itself without a residual head."""
        if self.residual is None:  # structural, fixed at construction: no branch in the graph
            return p
        return p + sign * self.residual(q)


class CompensatorGraph(nn.Module):
    """``q_nominal (B, N)`` rad -> ``q_corrected (B, N)`` rad (see the module docstring).

    Args:
        model: the calibrated :class:`ErrorModel` (its instrument frame is not used).
        x: calibrated parameter vector (SI).
        residual: optional module ``q (B, N) rad -> TCP position error (B, 3)`` in ``base``, m,
            predicted by a learned head (``StoredModel.residual.to_torch_module()``).
        dtype: float64 or float32 (inputs and outputs use it too).
        iterations: damped Newton steps, each with a fresh Jacobian.
        damping_gain: ``c`` of the error-dependent damping ``lambda^2 = c |e|^2 + lambda_0^2``.
        damping_floor: ``lambda_0`` (m per rad, rad per rad).
        solver: ``"inverse"`` (onnxruntime's contrib ``Inverse``, default) or ``"gauss_jordan"``
            (standard ONNX operators only, for other runtimes); both solve in float64.
        joint_errors: the model's joint-space errors (gravity compliance, harmonics), if any: the
            calibrated chain then turns by ``q + dq(q)`` (:mod:`torchcal.compensate.joint_error_graph`).
        device: where the constants live (CPU by default).
    """

    def __init__(
        self,
        model: ErrorModel,
        x: torch.Tensor,
        residual: nn.Module | None = None,
        *,
        dtype: torch.dtype = torch.float64,
        iterations: int = DEFAULT_ITERATIONS,
        damping_gain: float = DEFAULT_DAMPING_GAIN,
        damping_floor: float = DEFAULT_DAMPING_FLOOR,
        solver: str = "inverse",
        joint_errors: JointSpaceErrors | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__()
        if iterations < 1:
            raise ValueError("iterations must be >= 1")
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {sorted(SOLVERS)}, got {solver!r}")
        self.models = _TwoModels(model, x, residual, dtype, device, joint_errors)
        self.iterations = int(iterations)
        self.solver = solver
        self.dtype = dtype
        # the solve's constants are float64 whatever the graph's dtype (see the module docstring)
        self.register_buffer("eye6", torch.eye(6, dtype=torch.float64, device=device))
        self.register_buffer("damping_floor_sq", torch.tensor(damping_floor**2, dtype=torch.float64, device=device))
        self.register_buffer("damping_gain", torch.tensor(damping_gain, dtype=torch.float64, device=device))

    @classmethod
    def from_stored(cls, stored, **options) -> "CompensatorGraph":
        """Build from a :class:`torchcal.model_store.StoredModel` (residual head and joint-space errors included)."""
        return cls(stored.model, stored.x, **stored_parts(stored), **options)

    def forward(self, q_nominal: torch.Tensor) -> torch.Tensor:
        return self.solve(q_nominal)

    def solve(self, q_nominal: torch.Tensor, wrench: torch.Tensor | None = None) -> torch.Tensor:
        """The fixed number of damped Newton steps from ``q_nominal`` (``wrench``: loaded graphs)."""
        target, pose, joint_frames, slope = self.models.nominal_and_calibrated(q_nominal)
        q = q_nominal
        for step in range(self.iterations):
            if step > 0:
                pose, joint_frames, slope = self.models.calibrated_at(q)
            q = q + self.step(target, pose, joint_frames, q, wrench, slope)
        return q

    def step(self, target: torch.Tensor, pose: torch.Tensor, joint_frames: torch.Tensor, q: torch.Tensor,
             wrench: torch.Tensor | None = None, slope: torch.Tensor | None = None) -> torch.Tensor:
        """One damped Newton step ``(B, N)`` rad: ``J^T (J J^T + lambda^2 I)^-1 e``."""
        error = self.pose_error(target, pose[:, :3, 3], pose[:, :3, :3], q).unsqueeze(-1)  # (B, 6, 1)
        return self.damped_step(command_jacobian_t(pose, joint_frames, slope), error)

    def damped_step(self, jac_t: torch.Tensor, error: torch.Tensor) -> torch.Tensor:
        """``J^T (J J^T + lambda^2 I)^-1 e`` ``(B, N)`` for ``J^T`` ``(B, N, 6)`` and ``e`` ``(B, 6, 1)``.

        Computed in float64; a float32 graph casts in and out (structural, fixed at construction).
        """
        wide = self.dtype != torch.float64
        if wide:
            jac_t, error = jac_t.to(torch.float64), error.to(torch.float64)
        lam2 = self.damping_gain * (error * error).sum(-2, keepdim=True) + self.damping_floor_sq  # (B, 1, 1)
        normal = jac_t.transpose(-1, -2) @ jac_t + lam2 * self.eye6
        step = (jac_t @ SOLVERS[self.solver](normal, error, self.eye6)).squeeze(-1)
        return step.to(self.dtype) if wide else step

    def pose_error(self, target: torch.Tensor, position: torch.Tensor, rotation: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``[p_t - p - r(q), vee(R_t R^T)]`` ``(B, 6)`` (m, rad), ``base`` frame, for the TCP at
        ``position`` ``(B, 3)`` with ``rotation`` ``(B, 3, 3)``."""
        dp = self.models.add_residual(target[:, :3, 3] - position, q, -1.0)
        e = target[:, :3, :3] @ rotation.transpose(-1, -2)
        skew = (e - e.transpose(-1, -2)).reshape(-1, 9)
        return torch.cat([dp, 0.5 * skew[:, [7, 2, 3]]], -1)


class MonitorGraph(nn.Module):
    """``q (B, N)`` rad -> predicted TCP error ``(B, 3)`` in ``base``, m.

    The error is where the calibrated model (plus the residual head) puts the TCP minus where the
    nominal model does: the ``dp(q)`` of the compensator's sign convention.
    """

    def __init__(
        self,
        model: ErrorModel,
        x: torch.Tensor,
        residual: nn.Module | None = None,
        *,
        dtype: torch.dtype = torch.float64,
        joint_errors: JointSpaceErrors | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__()
        self.models = _TwoModels(model, x, residual, dtype, device, joint_errors)

    @classmethod
    def from_stored(cls, stored, **options) -> "MonitorGraph":
        return cls(stored.model, stored.x, **stored_parts(stored), **options)

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        if self.models.joint_errors is None:  # the fast path: positions only, no link tensors
            p = self.models.both.positions(q)
            return self.models.add_residual(p[:, 1] - p[:, 0], q)
        nominal, pose, _, _ = self.models.nominal_and_calibrated(q)
        return self.models.add_residual(pose[:, :3, 3] - nominal[:, :3, 3], q)


class LoadedCompensatorGraph(CompensatorGraph):
    """``(q_nominal (B, N) rad, wrench (B, 6)) -> q_corrected (B, N) rad``: geometry, residual and stiffness.

    The corrected command puts the *loaded* calibrated TCP on the nominal target: with the
    first-order deflection ``(dp, dphi)`` of :class:`~torchcal.compensate.deflection.DeflectionGraph`
    at the current iterate, ``p_cal + r + dp = p_t`` and ``exp([dphi]x) R_cal = R_t``. The wrench
    is ``[fx, fy, fz]`` N at the TCP and ``[tx, ty, tz]`` N m about it, along the tool axes (or the
    base axes with ``wrench_frame="base"``). The Newton steps keep the rigid Jacobian: the
    deflection changes with ``q`` by ~1e-3 of the arm's own motion, so it slows the contraction
    by that factor only (as the residual head does).

    Args:
        compliance: ``(N, 6, 6)`` joint compliance, SI (the model folder's stiffness stage).
        Other arguments: those of :class:`CompensatorGraph`.
    """

    def __init__(
        self,
        model: ErrorModel,
        x: torch.Tensor,
        compliance: torch.Tensor,
        residual: nn.Module | None = None,
        *,
        wrench_frame: str = "tool",
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
        **options,
    ) -> None:
        super().__init__(model, x, residual, dtype=dtype, device=device, **options)
        self.deflection = DeflectionGraph(compliance, wrench_frame=wrench_frame, dtype=dtype, device=device)

    @classmethod
    def from_stored(cls, stored, **options) -> "LoadedCompensatorGraph":
        """Build from a :class:`torchcal.model_store.StoredModel` with a stiffness stage."""
        return cls(stored.model, stored.x, stored.stiffness.compliance, **stored_parts(stored), **options)

    def forward(self, q_nominal: torch.Tensor, wrench: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        return self.solve(q_nominal, wrench)

    def step(self, target: torch.Tensor, pose: torch.Tensor, joint_frames: torch.Tensor, q: torch.Tensor,
             wrench: torch.Tensor | None = None, slope: torch.Tensor | None = None) -> torch.Tensor:
        """The rigid step with the error measured at the loaded TCP (Jacobian kept rigid)."""
        position, rotation = self.deflection.loaded_pose(pose, joint_frames, wrench)
        error = self.pose_error(target, position, rotation, q).unsqueeze(-1)
        return self.damped_step(command_jacobian_t(pose, joint_frames, slope), error)


class LoadedMonitorGraph(MonitorGraph):
    """``(q (B, N) rad, wrench (B, 6)) -> `` predicted loaded TCP error ``(B, 3)`` in ``base``, m.

    ``p_cal(q) + r(q) + dp(q, W) - p_nom(q)``: where the loaded real TCP lies relative to the
    nominal, unloaded one (the wrench as for :class:`LoadedCompensatorGraph`).
    """

    def __init__(
        self,
        model: ErrorModel,
        x: torch.Tensor,
        compliance: torch.Tensor,
        residual: nn.Module | None = None,
        *,
        wrench_frame: str = "tool",
        dtype: torch.dtype = torch.float64,
        joint_errors: JointSpaceErrors | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__(model, x, residual, dtype=dtype, joint_errors=joint_errors, device=device)
        self.deflection = DeflectionGraph(compliance, wrench_frame=wrench_frame, dtype=dtype, device=device)

    @classmethod
    def from_stored(cls, stored, **options) -> "LoadedMonitorGraph":
        return cls(stored.model, stored.x, stored.stiffness.compliance, **stored_parts(stored), **options)

    def forward(self, q: torch.Tensor, wrench: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        nominal, pose, frames, _ = self.models.nominal_and_calibrated(q)
        dp, _ = self.deflection(pose, frames, wrench)
        return self.models.add_residual(pose[:, :3, 3] - nominal[:, :3, 3] + dp, q)
