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

**Iterations.** Each pose steps until it has converged (:data:`CONVERGED_POSITION_M`, and
:data:`CONVERGED_ORIENTATION_RAD` in the steps that move the orientation), at most
``iterations`` steps; a converged pose keeps its command while the rest of its batch steps on, so
its result does not depend on the batch. Regular poses take two or three steps (most of them two), the
wrist singular ones four. The exported graph runs each phase of steps (mixed, then position-only) as an
ONNX ``Loop`` whose body is :meth:`CompensatorGraph.iterate` (:mod:`torchcal.compensate.loop_graph`).
The manifest's ``convergence`` (:func:`torchcal.compensate.export_checks.convergence_report`) shows what
the steps reach over the joint range, with the singular neighbourhoods as separate strata.

**Compact graph.** The graph computes in float64 whatever its interface, and each step is a few
dozen onnxruntime nodes: the calibrated chain's links from one Sin and two products
(:meth:`~torchcal.compensate.chain.ChainGraph.single`), the Jacobian in eight nodes from the
flattened frames (:func:`~torchcal.compensate.chain.geometric_jacobian_t`), the pose error as one
product of the TCP pose with weights fixed by the target once per call (:func:`_target_weights`),
and the step's solves sharing one Gram matrix (:func:`~torchcal.compensate.steps.position_first_step`).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar, Self

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
from torchcal.stages.orientation import orientation_source_of

if TYPE_CHECKING:  # annotations only
    from torchcal.stages.base import ModelStage

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
CONVERGED_POSITION_M = 1e-9
"""A pose stops stepping once its TCP position error is below this (m; 1e-3 of the 1 um that the
guarantees speak of) and, in the steps that move the orientation, its rotation error below
:data:`CONVERGED_ORIENTATION_RAD`. Tighter tolerances (1e-10 m and rad) cost a third step on most
regular poses (the orientation converges linearly under its damping floor) and about a quarter
of the graph's latency, for nothing a tool can feel (``scripts/bench_onnx.py``, docs/export.md)."""
CONVERGED_ORIENTATION_RAD = 1e-7
"""Rotation error (rad) below which a step that moves the orientation has converged: 0.1 um at a
1 m lever, far below any tool's or measurement's orientation."""
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


def graph_parts(stages: Sequence[ModelStage], inputs: tuple[str, ...] = ()) -> dict[str, Any]:
    """Keyword arguments of the graphs from a model's stages (``StoredModel.stages()``): their pieces
    (:meth:`~torchcal.stages.base.ModelStage.graph_part`: the chain, the joint-space errors, the
    residual head, the compliance), so that no constructor can drop one.

    ``inputs``: the inputs the graph takes beyond the joints; a stage that needs another (the
    stiffness stage's wrench) gives no piece to a graph without it."""
    parts: dict[str, Any] = {}
    for stage in stages:
        if set(stage.graph_inputs) <= set(inputs):
            parts.update(stage.graph_part())
    return parts


def graph_inputs(stages: Sequence[ModelStage]) -> tuple[str, ...]:
    """The inputs a model's graphs take beyond the joints, in stage order (``()`` or ``("wrench",)``)."""
    return tuple(name for stage in stages for name in stage.graph_inputs)


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

    turn_selector: torch.Tensor  # buffers (with joint-space errors): declared for the type checker
    gravity_point_shift: torch.Tensor

    def __init__(self, model: ErrorModel, x: torch.Tensor, residual: nn.Module | None, dtype: torch.dtype, device,
                 joint_errors: JointSpaceErrors | None = None, orient_by_geometry: bool = False) -> None:
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
        self.shifts_gravity_point = False
        self.orient_by_geometry = False
        if joint_errors is not None and not joint_errors.empty:
            self.joint_errors = JointErrorGraph(joint_errors, robot.dof, dtype=dtype, device=device)
            self.nominal = ChainGraph(tables[:1], t0, end_nominal.unsqueeze(0), dtype=dtype, device=device)
            self.orient_by_geometry = bool(orient_by_geometry)
            # a gravity term's 'tcp' point where it was fitted, from the nominal TCP: p + R (point - tool)
            point = None if joint_errors.compliance is None else joint_errors.compliance.tcp_point
            self.shifts_gravity_point = point is not None
            if point is not None:
                shift = point.to(torch.float64) - robot.tool.to(torch.float64)
                self.register_buffer("gravity_point_shift", shift.reshape(3, 1).to(device=device, dtype=dtype))
            # picks the joint axes z_i (entries 2, 6, 10 of a row-major frame) into the orientation rows of an error
            selector = torch.zeros(16, 6, dtype=dtype, device=device)
            for r in range(3):
                selector[4 * r + 2, 3 + r] = 1.0
            self.register_buffer("turn_selector", selector)

    def nominal_and_calibrated(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None,
                                                              torch.Tensor | None]:
        """Nominal TCP pose ``(B, 4, 4)`` at ``q``, the calibrated TCP pose and joint frames
        ``(B, N, 4, 4)`` at ``q + dq(q)``, the joint errors' slope ``(B, N)`` and the tool's turn by
        them (:meth:`turn`), each ``None`` where it does not apply; ``base``, m."""
        if self.joint_errors is None:
            poses, frames = self.both(q, with_frames=True)
            return poses[:, 0], poses[:, 1], frames[:, 1], None, None
        nominal, nominal_frames = self.nominal(q, with_frames=True)
        nominal = nominal[:, 0]
        point = nominal[:, :3, 3]
        if self.shifts_gravity_point:  # structural, fixed at construction
            point = point + (nominal[:, :3, :3] @ self.gravity_point_shift)[..., 0]
        dq, slope = self.joint_errors(q, nominal_frames[:, 0], point)
        pose, frames = self.calibrated.single(q + dq)
        return nominal, pose.reshape(-1, 4, 4), frames, slope, self.turn(frames, dq)

    def calibrated_at(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """Calibrated TCP pose ``(B, 4, 4)`` or ``(B, 1, 4, 4)`` (the Jacobian and the error read
        it flattened: no node spent on the axis) and joint frames at ``q + dq(q)``, the slope and the turn (or ``None``)."""
        if self.joint_errors is not None and self.joint_errors.needs_frames:
            return self.nominal_and_calibrated(q)[1:]
        slope = turn = None
        if self.joint_errors is not None:
            dq, slope = self.joint_errors(q)
            q = q + dq
        pose, frames = self.calibrated.single(q)
        if self.joint_errors is not None:
            turn = self.turn(frames, dq)
        return pose, frames, slope, turn

    def turn(self, frames: torch.Tensor, dq: torch.Tensor) -> torch.Tensor | None:
        """``(B, 6, 1)``: zeros and the rotation ``sum_i z_i dq_i`` (rad, ``base``) by which the joint-space
        errors ``dq`` ``(B, N)`` turn the tool, where the graph orients by the geometry alone (else ``None``).

        Added to an orientation error of the full chain it gives the geometric chain's to first
        order in ``dq``: at the solution (the error near zero) the remainder is of order ``|dq|^2``
        (1e-6 rad for 1e-3 rad of joint-space error); further from it a cross term of order
        ``|e| |dq|`` joins it, which the steps remove as ``e`` vanishes.
        """
        if not self.orient_by_geometry:  # structural, fixed at construction
            return None
        n = frames.shape[-3]
        return (dq.unsqueeze(1) @ frames.reshape(-1, n, 16) @ self.turn_selector).reshape(-1, 6, 1)

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
        dtype: float64 or float32, of the inputs and outputs. The graph computes in float64 in
            either case (a float32 graph casts its inputs up and its outputs down): the compact
            graph costs the same in float64, and float32 kinematics would leave ~1e-7 m of rounding.
        task: ``"position"`` (position first, orientation secondary; default) or ``"pose"``
            (full 6-D damped least squares).
        iterations: the most Newton steps, each with a fresh Jacobian (default:
            :data:`DEFAULT_ITERATIONS`); a pose stops stepping once it has converged
            (:data:`CONVERGED_POSITION_M`, :data:`CONVERGED_ORIENTATION_RAD`).
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
        tool_length: m; ``L > 0`` keeps the nominal command wherever the corrected one would leave a
            point up to ``L`` beyond the TCP further off than it, by the bound ``|e_p| + L theta``
            (position error plus lever times the tool's orientation deviation): where the position
            can be held only by turning the wrist (near the elbow, shoulder or wrist singularity)
            a tool would otherwise miss by its length times the turn. ``0`` (default): the TCP's
            position alone is judged.
        converged_position_m, converged_orientation_rad: the tolerances of the convergence test
            (default :data:`CONVERGED_POSITION_M`, :data:`CONVERGED_ORIENTATION_RAD`); tighter ones
            serve finite differences of the solved command (:func:`~torchcal.compensate.production_tcp.correction_sigma`).
        orientation_source: ``"model"`` (the whole calibrated chain) or ``"geometry"`` (its MDH table
            alone: the joint-space errors correct the position, not the tool's orientation); ``None``
            (default): :func:`~torchcal.stages.orientation.orientation_source_of`. Without joint-space errors the two are the same.
        device: where the constants live (CPU by default).
    """

    inputs: ClassVar[tuple[str, ...]] = ()
    """Inputs beyond the joints (see :func:`graph_parts`)."""
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
    target_weights: torch.Tensor
    one: torch.Tensor
    blocks: torch.Tensor
    is_position_row: torch.Tensor
    scores_both: torch.Tensor
    scores_position: torch.Tensor

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
        tool_length: float = 0.0,
        converged_position_m: float = CONVERGED_POSITION_M,
        converged_orientation_rad: float = CONVERGED_ORIENTATION_RAD,
        orientation_source: str | None = None,
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
        if not (converged_position_m > 0 and converged_orientation_rad > 0):
            raise ValueError(f"the convergence tolerances must be > 0, got {converged_position_m} m, {converged_orientation_rad} rad")
        if not (math.isfinite(tool_length) and tool_length >= 0):
            raise ValueError(f"tool_length must be a finite length >= 0 m, got {tool_length}")
        self.tool_length = float(tool_length)
        self.orientation_source = orientation_source_of(model, orientation_source)
        # float64 inside whatever the interface (see ``dtype`` above)
        self.models = _TwoModels(model, x, residual, torch.float64, device, joint_errors,
                                 orient_by_geometry=self.orientation_source == "geometry")
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
        self.register_buffer("lower", limits[:, 0].to(device=device))
        self.register_buffer("upper", limits[:, 1].to(device=device))
        self.register_buffer("target_weights", _target_weights().to(device))
        # squared-error scores of the convergence test: position and orientation rows of e e
        blocks = torch.zeros(2, 6, **f64)
        blocks[0, :3] = blocks[1, 3:] = 1.0
        self.register_buffer("one", torch.tensor(1.0, **f64))  # a float64 constant: no Cast node in the test
        self.register_buffer("blocks", blocks)  # sums of e e: |e_p|^2, |e_o|^2
        self.register_buffer("is_position_row", torch.tensor([[True], [False]], device=device))
        self.tolerances = (float(converged_position_m), float(converged_orientation_rad))
        scores = blocks / torch.tensor([[converged_position_m**2], [converged_orientation_rad**2]], **f64)
        self.register_buffer("scores_both", scores)
        self.register_buffer("scores_position", scores[:1].clone())

    @classmethod
    def from_stored(cls, stored, **options) -> Self:
        """Build from a :class:`torchcal.stages.store.StoredModel`: every stage's piece that this class's
        :attr:`inputs` can take (a loaded graph also its stiffness)."""
        return cls(**graph_parts(stored.stages(), cls.inputs), **options)

    def forward(self, q_nominal: torch.Tensor) -> torch.Tensor:
        return self.solve(q_nominal)[0]

    @property
    def phases(self) -> list[tuple[bool, int]]:
        """``(orientation, most steps)`` of each phase: the mixed steps, then the position-only ones."""
        if self.task == "pose":
            return [(True, self.iterations)]
        phases = [(True, self.orientation_steps)]
        if self.iterations > self.orientation_steps:
            phases.append((False, self.iterations - self.orientation_steps))
        return phases

    def solve(self, q_nominal: torch.Tensor, wrench: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Steps from ``q_nominal`` until each pose has converged, at most :attr:`iterations` (``wrench``: loaded graphs).

        Returns ``q_corrected`` ``(B, N)`` rad and the ``residual`` ``(B, 2)``: the remaining
        position error (m) and orientation deviation (rad) of the model at ``q_corrected``.
        The exported graph runs the same parts (:meth:`start`, :meth:`iterate`, :meth:`pending`,
        :meth:`finish`), each phase's steps as one ONNX ``Loop`` (:mod:`torchcal.compensate.loop_graph`).
        A step here takes only the poses not yet converged (the ``Loop`` steps the whole batch and
        keeps the converged poses' commands): a third less work over the joint range, the same
        steps pose by pose. Products over a smaller batch may round differently in the last bit
        (measured: one pose in 600 or 20000 whose command differs, by 5e-15 rad at most; residuals
        within 3e-16 m).
        """
        q_in, wrench = self.widen(q_nominal, wrench)
        weights, before, q, jac_t, error = self.start(q_in, wrench)
        for orientation, steps in self.phases:
            score = self.score(error, orientation)
            for _ in range(steps):
                rows = (score >= self.one)[:, 0].nonzero()[:, 0]
                if not len(rows):
                    break
                _, q_r, jac_r, error_r, score_r = self.iterate(q[rows], jac_t[rows], error[rows], score[rows], weights[rows],
                                                               None if wrench is None else wrench[rows], orientation)
                q, jac_t = q.index_copy(0, rows, q_r), jac_t.index_copy(0, rows, jac_r)
                error, score = error.index_copy(0, rows, error_r), score.index_copy(0, rows, score_r)
        return self.narrow(*self.finish(q_in, before, q, error))

    def nominal_residual(self, q_nominal: torch.Tensor, wrench: torch.Tensor | None = None) -> torch.Tensor:
        """``(B, 2)``: what the nominal command leaves, by the model (position error, m; orientation
        deviation from the nominal target, rad): :meth:`solve`'s ``residual`` had nothing been corrected."""
        q_in, wrench = self.widen(q_nominal, wrench)
        return self.remaining(self.start(q_in, wrench)[1])[..., 0]

    def narrow(self, q_c: torch.Tensor, residual: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The outputs in the graph's dtype (a float32 graph's two Cast nodes)."""
        if self.dtype == torch.float64:
            return q_c, residual
        return q_c.to(self.dtype), residual.to(self.dtype)

    def widen(self, q_nominal: torch.Tensor, wrench: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The inputs in float64 (a float32 graph's two Cast nodes)."""
        if self.dtype == torch.float64:
            return q_nominal, wrench
        return q_nominal.to(torch.float64), None if wrench is None else wrench.to(torch.float64)

    def start(self, q_nominal: torch.Tensor, wrench: torch.Tensor | None):
        """Before the first step: the target's error weights ``(B, 6, 16)``, the error of the
        nominal command ``(B, 6, 1)`` (``before``), and the iterate: ``q``, ``J^T`` ``(B, N, 6)``, error."""
        target, pose, joint_frames, slope, turn = self.models.nominal_and_calibrated(q_nominal)
        weights = (target.reshape(-1, 16) @ self.target_weights).reshape(-1, 6, 16)
        error = self.loaded_error(weights, pose, joint_frames, q_nominal, wrench, turn)
        return weights, error, q_nominal, command_jacobian_t(pose, joint_frames, slope), error

    def score(self, error: torch.Tensor, orientation: bool) -> torch.Tensor:
        """``(B, 1)``: the largest of ``|e_p|^2 / tol_p^2`` and (``orientation``) ``|e_o|^2 / tol_o^2``; below 1: converged."""
        weights = self.scores_both if orientation else self.scores_position
        return (weights @ (error * error)).amax(1)

    def pending(self, score: torch.Tensor) -> torch.Tensor:
        """Whether any pose of the batch has not converged (a 0-d bool, the ``Loop``'s condition)."""
        return score.amax() >= self.one

    def iterate(self, q: torch.Tensor, jac_t: torch.Tensor, error: torch.Tensor, score: torch.Tensor, weights: torch.Tensor,
                wrench: torch.Tensor | None, orientation: bool):
        """One step of every pose not yet converged (the converged ones keep their command, so a
        pose's result does not depend on its batch), then the kinematics at the new commands.

        Returns ``(pending, q, J^T, error, score)`` at the new commands.
        """
        dq = self.step(jac_t, error, orientation=orientation)
        stepped = torch.minimum(torch.maximum(q + dq, self.lower), self.upper)
        q = torch.where(score < self.one, q, stepped)
        pose, joint_frames, slope, turn = self.models.calibrated_at(q)
        error = self.loaded_error(weights, pose, joint_frames, q, wrench, turn)
        score = self.score(error, orientation)
        return self.pending(score), q, command_jacobian_t(pose, joint_frames, slope), error, score

    def finish(self, q_nominal: torch.Tensor, before: torch.Tensor, q: torch.Tensor, error: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The command and ``residual`` ``(B, 2)``: ``q``, or the nominal command where the steps
        ended further from the target than it (a joint limit, the arm's reach)."""
        # the error at q came through the kinematics after the last step: where the iteration did
        # not converge (near a singularity) a prediction from the last step would say it did
        both = self.remaining(torch.cat([before, error], -1))  # (B, 2, 2): [position, turn] x [before, after]
        if self.tool_length > 0:  # structural: the default graph judges the position alone
            bound = both[:, :1] + self.tool_length * both[:, 1:]  # (B, 1, 2): |e_p| + L theta, before and after
            better = bound[..., 1] <= bound[..., 0]
        else:
            better = both[:, :1, 1] <= both[:, :1, 0]
        return torch.where(better, q, q_nominal), torch.where(better, both[..., 1], both[..., 0])

    def step(self, jac_t: torch.Tensor, error: torch.Tensor, orientation: bool = True) -> torch.Tensor:
        """One step ``(B, N)`` rad of the graph's task (float64: see ``dtype``)."""
        if self.task == "pose":
            return pose_step(jac_t, error, self.damping_gain, self.damping_floor_sq, self.eye6, SOLVERS[self.solver])
        return position_first_step(jac_t, error, self.damping_gain, self.damping_floor_sq, self.orientation_damping_sq,
                                   self.eye3, self.max_step, self.max_orientation_step, orientation=orientation,
                                   inverse=INVERSES3[self.solver])

    def remaining(self, error: torch.Tensor) -> torch.Tensor:
        """``(B, 2, K)`` from errors ``(B, 6, K)``: position error norm (m) and the orientation
        deviation angle (rad; the rotation error is ``sin(angle) axis``) of each column."""
        norms = (self.blocks @ (error * error)).sqrt()  # (B, 2, K)
        # onnxruntime has Asin for float32 only: float32 is ample for a reported angle (1e-7 relative)
        turn = torch.asin(torch.clamp(norms, max=1.0).float()).to(norms.dtype)
        return torch.where(self.is_position_row, norms, turn)

    def loaded_error(self, weights: torch.Tensor, pose: torch.Tensor, joint_frames: torch.Tensor, q: torch.Tensor,
                     wrench: torch.Tensor | None, turn: torch.Tensor | None = None) -> torch.Tensor:
        """``[p_t - p - r(q), vee(R_t R^T)]`` ``(B, 6, 1)`` (m, rad, ``base``) of the calibrated TCP
        ``pose`` ``(B, 4, 4)``: linear in the pose, ``weights @ vec(pose)`` with the target's
        ``weights`` (:func:`_target_weights`), one product per iterate. With the joint-space errors'
        ``turn`` (:meth:`_TwoModels.turn`) the orientation rows are the geometric chain's."""
        error = weights @ pose.reshape(-1, 16, 1)
        if turn is not None:  # structural, fixed at construction
            error = error + turn
        if self.models.residual is None:  # structural, fixed at construction
            return error
        return error - torch.nn.functional.pad(self.models.residual(q), (0, 3)).unsqueeze(-1)


def _target_weights() -> torch.Tensor:
    """``(16, 96)``: the target pose (row-major, ``(B, 16)``) times it is the ``(B, 6, 16)`` matrix
    ``W`` with ``W vec(T) = [p_t - p, vee(R_t R^T)]`` for a TCP pose ``T`` (``vee`` of the skew
    part, ``0.5 (A - A^T)`` with ``A = R_t R^T``; the homogeneous 1 of either pose carries the
    constant terms)."""
    w = torch.zeros(16, 6, 16, dtype=torch.float64)
    for r in range(3):
        w[4 * r + 3, r, 15] = 1.0  # + p_t (T[15] = 1)
        w[15, r, 4 * r + 3] = -1.0  # - p   (T_t[15] = 1)
    # e_o = 0.5 [A21 - A12, A02 - A20, A10 - A01], A_ij = sum_k Rt_ik R_jk
    for row, (i, j) in enumerate(((2, 1), (0, 2), (1, 0))):
        for k in range(3):
            w[4 * i + k, 3 + row, 4 * j + k] += 0.5
            w[4 * j + k, 3 + row, 4 * i + k] -= 0.5
    return w.reshape(16, 96)


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

    inputs: ClassVar[tuple[str, ...]] = ()

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
    def from_stored(cls, stored, **options) -> Self:
        """Build from a :class:`torchcal.stages.store.StoredModel` (as :meth:`CompensatorGraph.from_stored`)."""
        return cls(**graph_parts(stored.stages(), cls.inputs), **options)

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        if self.models.joint_errors is None:  # the fast path: positions only, no link tensors
            p = self.models.both.positions(q)
            return self.models.add_residual(p[:, 1] - p[:, 0], q)
        nominal, pose, _, _, _ = self.models.nominal_and_calibrated(q)
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

    inputs: ClassVar[tuple[str, ...]] = ("wrench",)

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
        self.deflection = DeflectionGraph(compliance, wrench_frame=wrench_frame, dtype=torch.float64, device=device)

    def forward(self, q_nominal: torch.Tensor, wrench: torch.Tensor) -> torch.Tensor:  # type: ignore[override]  # wrench: 2nd graph input
        return self.solve(q_nominal, wrench)[0]

    def loaded_error(self, weights: torch.Tensor, pose: torch.Tensor, joint_frames: torch.Tensor, q: torch.Tensor,
                     wrench: torch.Tensor | None, turn: torch.Tensor | None = None) -> torch.Tensor:
        """The error measured at the loaded TCP (the Jacobian stays rigid)."""
        if wrench is None:
            raise ValueError("a loaded compensator needs the wrench")
        pose = pose.reshape(-1, 4, 4)
        position, rotation = self.deflection.loaded_pose(pose, joint_frames, wrench)
        loaded = torch.cat([torch.cat([rotation, position.unsqueeze(-1)], -1), pose[:, 3:]], 1)
        return super().loaded_error(weights, loaded, joint_frames, q, wrench, turn)


class LoadedMonitorGraph(MonitorGraph):
    """``(q (B, N) rad, wrench (B, 6)) -> `` predicted loaded TCP error ``(B, 3)`` in ``base``, m.

    ``p_cal(q) + r(q) + dp(q, W) - p_nom(q)``: where the loaded real TCP lies relative to the
    nominal, unloaded one (the wrench as for :class:`LoadedCompensatorGraph`).
    """

    inputs: ClassVar[tuple[str, ...]] = ("wrench",)

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

    def forward(self, q: torch.Tensor, wrench: torch.Tensor) -> torch.Tensor:  # type: ignore[override]  # wrench: 2nd graph input
        nominal, pose, frames, _, _ = self.models.nominal_and_calibrated(q)
        dp, _ = self.deflection(pose, frames, wrench)
        return self.models.add_residual(pose[:, :3, 3] - nominal[:, :3, 3] + dp, q)


#: The compensator and monitor classes by the inputs the model's stages add beyond the joints
#: (:func:`graph_inputs`): a stage with a new input brings its graph classes and one line here.
GRAPH_CLASSES: dict[tuple[str, ...], tuple[type[CompensatorGraph], type[MonitorGraph]]] = {
    (): (CompensatorGraph, MonitorGraph),
    ("wrench",): (LoadedCompensatorGraph, LoadedMonitorGraph),
}
