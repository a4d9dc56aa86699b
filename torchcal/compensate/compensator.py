"""The compensator and monitor graphs: plain ``torch.nn.Module`` s with a fixed op sequence.

Frames: everything is in the calibrated robot ``base`` frame; the instrument transform of the
calibration (``T_instrument_base``) is not part of either graph. Units: joints in rad, lengths
in m.

**What the compensator solves.** The controller believes the nominal model: for a nominal
command ``q_t`` it expects the tool at ``T_t = T_nom(q_t)`` (nominal ``flange_pose(q_t) @ tool``).
The calibrated model (geometry ``x``, joint-space errors, and the optional learned residual
``r(q)``, a TCP position error in ``base``, m) says where the tool really goes. The corrected
command ``q_c`` is the one that puts the calibrated TCP on the believed target::

    p_cal(q_c) + r(q_c) = p_t            (position: always first)
    R_cal(q_c) = R_t                     (orientation: as far as the position task leaves room)

**Sign convention** (that of the compensation patents): the predicted error of a command is
``dT(q) = T_real(q) - T_nom(q)``, for positions ``dp(q) = p_cal(q) + r(q) - p_nom(q)`` (the
:class:`MonitorGraph` output). The compensated target is ``T_c = T_t - dT`` and the command is its
nominal inverse kinematics ``q_c = IK_nom(T_c)``. The patents evaluate ``dT`` once at ``q_t``;
solving the equations above is the fixed point of that rule with ``dT`` taken at ``q_c`` itself,
so that ``p_nom(q_c) = p_t - dp(q_c)`` holds exactly (tested).

**Tasks** (:data:`TASKS`; :mod:`torchcal.compensate.steps` has the steps):

* ``"position"`` (default): task-priority damped least squares. Each step solves the position
  equations and moves the orientation only in what the position leaves free; the last
  :data:`POSITION_ONLY_STEPS` steps are position-only, so that the second-order position change
  of an orientation move is removed. The wrist singularity is a singularity of orientation only:
  there the position is still solved to rounding, and the orientation deviation that the bounded
  wrist motion cannot remove is an output of the graph (:data:`RESIDUAL_OUTPUT`).
* ``"pose"``: damped least squares on the full 6-D pose (one 6x6 solve per step, float64,
  onnxruntime's ``Inverse`` node or an unrolled Gauss-Jordan: :mod:`torchcal.compensate.linalg`).
  For users who need the orientation exactly; near a wrist singularity its shared damping
  corrects the position only partially.

Every step is bounded (no joint moves more than ``max_step`` rad per step) and every iterate is
kept inside the joint limits. Where the steps end further from the target than the nominal
command is (a target beyond a joint limit or beyond the real arm's reach), the graph returns the
nominal command: compensation never makes a command worse, by the model's own account.

The damping follows the error, ``lambda^2 = c |e|^2 + lambda_0^2`` (Sugihara's rule): large while the error is large, vanishing as it does, so regular poses
converge quadratically. The residual's own Jacobian is left out of the step: a learned error of
~0.1 mm varies by ~1e-4 m/rad against ~1 m/rad for the arm, so it only slows the contraction by
~1e-4 per step. The solves run in float64 in every variant: a float32 graph casts ``J`` and ``e``
up and the step back down (in float32, ``J^T J`` loses the small singular values of a
near-singular pose to rounding).

**The second output** ``residual`` ``(B, 2)``: the model's remaining TCP position error (m) and
orientation deviation (rad) at ``q_c``, through the kinematics once more after the last step (a
first-order prediction from the last step would call an oscillating, unconverged pose solved).
A controller reads from it whether a command was solved (position below its tolerance) and how
far the tool is turned from the nominal orientation.

The iteration count is fixed (no data-dependent control flow in the graph). The manifest's
``convergence`` (:func:`torchcal.compensate.export.convergence_report`) shows what it reaches
over the joint range, with the singular neighbourhoods as separate strata.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from torch import nn

from torchcal.compensate.chain import ChainGraph, geometric_jacobian_t
from torchcal.compensate.deflection import DeflectionGraph
from torchcal.compensate.joint_error_graph import JointErrorGraph
from torchcal.compensate.linalg import gauss_jordan, inverse3, ort_inverse, ort_solve
from torchcal.compensate.steps import pose_step, position_first_step
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import RobotModel

TASKS = ("position", "pose")
DEFAULT_TASK = "position"
DEFAULT_ITERATIONS = {"position": 6, "pose": 3}
"""Steps per task: chosen by the convergence table (``scripts/bench_onnx.py``, docs/export.md)."""
POSITION_ONLY_STEPS = 3
"""The last steps of the position task move the position only (at most ``iterations - 1``)."""
DEFAULT_DAMPING_GAIN = {"position": 0.1, "pose": 10.0}
DEFAULT_DAMPING_FLOOR = 1e-5
DEFAULT_ORIENTATION_DAMPING = 0.01
"""Floor of the secondary (orientation) task's damping, rad/rad: bounds the wrist's swing."""
DEFAULT_MAX_STEP = 0.1
"""Largest joint move of one step (of the position part of a position-first step), rad."""
DEFAULT_MAX_ORIENTATION_STEP = 0.02
"""Largest joint move of the orientation part of a position-first step, rad."""
RESIDUAL_OUTPUT = "residual"
"""Second output of the compensator: ``(B, 2)`` remaining TCP position error (m) and orientation deviation (rad)."""
SOLVERS = {"inverse": ort_solve, "gauss_jordan": gauss_jordan}
"""The 6x6 solve of a ``pose`` step: onnxruntime's ``Inverse`` node, or the portable unrolled elimination."""
INVERSES3 = {"inverse": ort_inverse, "gauss_jordan": inverse3}
"""The 3x3 inverses of a ``position`` step: onnxruntime's ``Inverse`` node, or the portable adjugate."""


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
    """Keyword arguments of the graphs from a :class:`~torchcal.stages.store.StoredModel`: its
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
        task: ``"position"`` (position first, orientation secondary; default) or ``"pose"``
            (full 6-D damped least squares).
        iterations: Newton steps, each with a fresh Jacobian (default: :data:`DEFAULT_ITERATIONS`).
        damping_gain: ``c`` of the error-dependent damping ``lambda^2 = c |e|^2 + lambda_0^2``
            (default: :data:`DEFAULT_DAMPING_GAIN` of the task).
        damping_floor: ``lambda_0`` (m per rad, rad per rad).
        orientation_damping: floor of the orientation task's damping (``position`` task), rad/rad.
        max_step: largest joint move per step (of its position part for the ``position`` task), rad.
        max_orientation_step: largest joint move of the orientation part of a ``position`` step, rad.
        position_only_steps: how many of the last steps of the ``position`` task are position-only
            (at least one step keeps the orientation task).
        solver: ``"inverse"`` (onnxruntime's contrib ``Inverse``, default) or ``"gauss_jordan"``
            (standard ONNX operators only: an unrolled elimination for the 6x6 solve of the
            ``pose`` task, the closed-form adjugate for the 3x3 solves of the ``position`` task).
        joint_errors: the model's joint-space errors (gravity compliance, harmonics), if any: the
            calibrated chain then turns by ``q + dq(q)`` (:mod:`torchcal.compensate.joint_error_graph`).
        device: where the constants live (CPU by default).
    """

    # buffers, registered in __init__ (declared so that type checkers see tensors, not Tensor | Module)
    eye6: torch.Tensor
    eye3: torch.Tensor
    damping_floor_sq: torch.Tensor
    damping_gain: torch.Tensor
    orientation_damping_sq: torch.Tensor
    max_step: torch.Tensor
    max_orientation_step: torch.Tensor
    lower: torch.Tensor
    upper: torch.Tensor

    def __init__(
        self,
        model: ErrorModel,
        x: torch.Tensor,
        residual: nn.Module | None = None,
        *,
        dtype: torch.dtype = torch.float64,
        task: str = DEFAULT_TASK,
        iterations: int | None = None,
        damping_gain: float | None = None,
        damping_floor: float = DEFAULT_DAMPING_FLOOR,
        orientation_damping: float = DEFAULT_ORIENTATION_DAMPING,
        max_step: float = DEFAULT_MAX_STEP,
        max_orientation_step: float = DEFAULT_MAX_ORIENTATION_STEP,
        position_only_steps: int = POSITION_ONLY_STEPS,
        solver: str = "inverse",
        joint_errors: JointSpaceErrors | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__()
        if task not in TASKS:
            raise ValueError(f"task must be one of {list(TASKS)}, got {task!r}")
        iterations = DEFAULT_ITERATIONS[task] if iterations is None else int(iterations)
        if iterations < 1:
            raise ValueError("iterations must be >= 1")
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {sorted(SOLVERS)}, got {solver!r}")
        if not (max_step > 0 and max_orientation_step > 0):
            raise ValueError(f"max_step and max_orientation_step must be > 0 rad, got {max_step}, {max_orientation_step}")
        self.models = _TwoModels(model, x, residual, dtype, device, joint_errors)
        self.task = task
        self.iterations = iterations
        # position task: orientation on the first steps, position alone on the last ones (at least one mixed step)
        self.orientation_steps = iterations if task == "pose" else max(1, iterations - int(position_only_steps))
        self.solver = solver
        self.dtype = dtype
        gain = DEFAULT_DAMPING_GAIN[task] if damping_gain is None else float(damping_gain)
        f64: dict[str, Any] = {"dtype": torch.float64, "device": device}
        # the solve's constants are float64 whatever the graph's dtype (see the module docstring)
        self.register_buffer("eye6", torch.eye(6, **f64))
        self.register_buffer("eye3", torch.eye(3, **f64))
        self.register_buffer("damping_floor_sq", torch.tensor(damping_floor**2, **f64))
        self.register_buffer("damping_gain", torch.tensor(gain, **f64))
        self.register_buffer("orientation_damping_sq", torch.tensor(orientation_damping**2, **f64))
        self.register_buffer("max_step", torch.tensor(max_step, **f64))
        self.register_buffer("max_orientation_step", torch.tensor(max_orientation_step, **f64))
        limits = model.robot.joint_limits.to(torch.float64)
        self.register_buffer("lower", limits[:, 0].to(device=device, dtype=dtype))
        self.register_buffer("upper", limits[:, 1].to(device=device, dtype=dtype))

    @classmethod
    def from_stored(cls, stored, **options) -> CompensatorGraph:
        """Build from a :class:`torchcal.stages.store.StoredModel` (residual head and joint-space errors included)."""
        return cls(stored.model, stored.x, **stored_parts(stored), **options)

    def forward(self, q_nominal: torch.Tensor) -> torch.Tensor:
        return self.solve(q_nominal)[0]

    def solve(self, q_nominal: torch.Tensor, wrench: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The fixed number of steps from ``q_nominal`` (``wrench``: loaded graphs).

        Returns ``q_corrected`` ``(B, N)`` rad and the ``residual`` ``(B, 2)``: the remaining
        position error (m) and orientation deviation (rad) of the model at ``q_corrected``.
        """
        target, pose, joint_frames, slope = self.models.nominal_and_calibrated(q_nominal)
        q = q_nominal
        error = self.loaded_error(target, pose, joint_frames, q, wrench)  # (B, 6, 1)
        before = self.remaining(error.squeeze(-1))
        for step in range(self.iterations):
            if step > 0:
                pose, joint_frames, slope = self.models.calibrated_at(q)
                error = self.loaded_error(target, pose, joint_frames, q, wrench)
            jac_t = command_jacobian_t(pose, joint_frames, slope)
            dq = self.step(jac_t, error, orientation=step < self.orientation_steps)
            q = torch.minimum(torch.maximum(q + dq, self.lower), self.upper)
        # what the command leaves, through the kinematics once more: where the iteration did not
        # converge (near a singularity) a prediction from the last step would say it did
        pose, joint_frames, _ = self.models.calibrated_at(q)
        after = self.remaining(self.loaded_error(target, pose, joint_frames, q, wrench).squeeze(-1))
        # never worse than no compensation: where a joint limit or the arm's reach stopped the
        # steps further from the target than the nominal command, the nominal command is returned
        better = after[:, :1] <= before[:, :1]
        return torch.where(better, q, q_nominal), torch.where(better, after, before)

    def loaded_error(self, target: torch.Tensor, pose: torch.Tensor, joint_frames: torch.Tensor, q: torch.Tensor,
                     wrench: torch.Tensor | None) -> torch.Tensor:
        """``[p_t - p - r(q), vee(R_t R^T)]`` ``(B, 6, 1)`` of the (unloaded) calibrated TCP ``pose``."""
        return self.pose_error(target, pose[:, :3, 3], pose[:, :3, :3], q).unsqueeze(-1)

    def step(self, jac_t: torch.Tensor, error: torch.Tensor, orientation: bool = True) -> torch.Tensor:
        """One step ``(B, N)`` rad of the graph's task, computed in float64 (a float32 graph casts in and out)."""
        wide = self.dtype != torch.float64
        if wide:
            jac_t, error = jac_t.to(torch.float64), error.to(torch.float64)
        if self.task == "pose":
            step = pose_step(jac_t, error, self.damping_gain, self.damping_floor_sq, self.eye6, SOLVERS[self.solver])
        else:
            step = position_first_step(jac_t, error, self.damping_gain, self.damping_floor_sq, self.orientation_damping_sq,
                                       self.eye3, self.max_step, self.max_orientation_step, orientation=orientation,
                                       inverse=INVERSES3[self.solver])
        return step.to(self.dtype) if wide else step

    def remaining(self, error: torch.Tensor) -> torch.Tensor:
        """``(B, 2)`` from the error ``(B, 6)`` at the command: position error norm (m) and the
        orientation deviation angle (rad; the rotation error is ``sin(angle) axis``)."""
        # onnxruntime has Asin for float32 only: float32 is ample for a reported angle (1e-7 relative)
        turn = torch.asin(torch.clamp(error[:, 3:].norm(dim=-1), max=1.0).float()).to(error.dtype)
        return torch.stack([error[:, :3].norm(dim=-1), turn], -1)

    def pose_error(self, target: torch.Tensor, position: torch.Tensor, rotation: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """``[p_t - p - r(q), vee(R_t R^T)]`` ``(B, 6)`` (m, rad), ``base`` frame, for the TCP at
        ``position`` ``(B, 3)`` with ``rotation`` ``(B, 3, 3)``."""
        dp = self.models.add_residual(target[:, :3, 3] - position, q, -1.0)
        e = target[:, :3, :3] @ rotation.transpose(-1, -2)
        skew = (e - e.transpose(-1, -2)).reshape(-1, 9)
        return torch.cat([dp, 0.5 * skew[:, [7, 2, 3]]], -1)


class CompensatorWithResidual(nn.Module):
    """The exported form of a compensator: ``forward`` returns ``(q_corrected, residual)``."""

    def __init__(self, graph: CompensatorGraph) -> None:
        super().__init__()
        self.graph = graph

    def forward(self, q_nominal: torch.Tensor, wrench: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        return self.graph.solve(q_nominal, wrench)


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
    def from_stored(cls, stored, **options) -> MonitorGraph:
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
    def from_stored(cls, stored, **options) -> LoadedCompensatorGraph:
        """Build from a :class:`torchcal.stages.store.StoredModel` with a stiffness stage."""
        return cls(stored.model, stored.x, stored.stiffness.compliance, **stored_parts(stored), **options)

    def forward(self, q_nominal: torch.Tensor, wrench: torch.Tensor) -> torch.Tensor:  # type: ignore[override]  # wrench: 2nd graph input
        return self.solve(q_nominal, wrench)[0]

    def loaded_error(self, target: torch.Tensor, pose: torch.Tensor, joint_frames: torch.Tensor, q: torch.Tensor,
                     wrench: torch.Tensor | None) -> torch.Tensor:
        """The error measured at the loaded TCP (the Jacobian stays rigid)."""
        if wrench is None:
            raise ValueError("a loaded compensator needs the wrench")
        position, rotation = self.deflection.loaded_pose(pose, joint_frames, wrench)
        return self.pose_error(target, position, rotation, q).unsqueeze(-1)


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
    def from_stored(cls, stored, **options) -> LoadedMonitorGraph:
        return cls(stored.model, stored.x, stored.stiffness.compliance, **stored_parts(stored), **options)

    def forward(self, q: torch.Tensor, wrench: torch.Tensor) -> torch.Tensor:  # type: ignore[override]  # wrench: 2nd graph input
        nominal, pose, frames, _ = self.models.nominal_and_calibrated(q)
        dp, _ = self.deflection(pose, frames, wrench)
        return self.models.add_residual(pose[:, :3, 3] - nominal[:, :3, 3] + dp, q)
