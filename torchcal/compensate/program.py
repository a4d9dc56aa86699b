"""Offline compensation of a robot program: joint targets in, corrected joint targets out.

Most users apply a calibration without a PC in the control loop: the targets of a robot program
are corrected once, offline, and loaded into the controller. This module runs the very
compensator that ``torchcal export`` writes to ONNX (:class:`~torchcal.compensate.compensator.
CompensatorGraph`, built by :func:`~torchcal.compensate.graphs.build_graphs`, float64) on the
program's targets, with the same safety limits:

* every step bounded and every command inside the joint limits (the graph's own);
* where the steps end further from the target than the nominal command is (beyond reach or a joint
  limit), the nominal command (the graph's own);
* the export's refusal: a model whose median joint correction or tool orientation deviation over
  its training poses exceeds the limits of :mod:`torchcal.compensate.production_tcp` is refused
  unless ``allow_large_corrections`` (the same check, :func:`check_corrections`);
* the command written is the compensator's own, as the exported runtime returns it; a target
  counts as corrected (``corrected`` 1) when the model's remaining TCP position error at that
  command is within :data:`SOLVED_WITHIN_M` (the export's convergence figure, 1 um). Any other
  target gets one line: *not solved to 1 um* where the command is the compensator's but leaves more
  (its remaining error and the nominal command's are stated), *nominal command kept* where the
  compensator returned the nominal command (its steps ended further off: beyond reach, a joint
  limit or a singularity).

Targets: ``q1..qN`` (deg), one row per target, the data contract's joint columns; other columns
(speed, zone...) are carried to the output as written, after its own. Or **TCP poses** with a start configuration: ``x, y, z`` (mm, the robot's base frame,
the production TCP) and optionally ``rx, ry, rz`` (deg, fixed-axis XYZ, the file convention), no
joint columns, and ``start_deg`` (``--start``): each pose's nominal joint target is found by the
project's inverse kinematics (:func:`torchcal.kinematics.ik.solve_ik`, on the nominal robot ending
in the production TCP) from the previous target's solution (the first from the start), so the
program keeps one arm configuration; those joint targets then go through the same compensator. A
pose the nominal robot cannot reach from there, or only outside its joint limits, is one line
naming its row (exit status 2). Output: ``q1..qN`` (deg, the compensator's command), ``corrected`` (1/0: solved to 1 um), ``correction_deg`` (the largest joint move), ``remaining_mm`` (the
model's remaining TCP error at the written command), then the program's other columns. It is written atomically with a sidecar
``<out>.torchcal.json`` (model, targets and output SHA-256, the settings, the summary); an
existing output is overwritten only when its sidecar says torchcal wrote it for this purpose and
its content is unchanged since.
"""

from __future__ import annotations

import csv
import io
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchcal.compensate.compensator import DEFAULT_TASK, TASKS
from torchcal.compensate.export import MAX_ITERATIONS
from torchcal.compensate.export_checks import regular_poses
from torchcal.compensate.graphs import (
    build_graphs,
    check_tool_length,
    compensator_of,
    has_wrench_input,
)
from torchcal.compensate.production_tcp import (
    check_corrections,
    correction_extent,
    production_view,
    tcp_transform,
)
from torchcal.core.errors import DataError, TorchcalError
from torchcal.core.hashing import sha256_bytes
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.core.outputs import refuse_inside_output
from torchcal.data.csv_table import check_joint_limits, joint_columns, read_csv_table
from torchcal.data.plausibility import check_joint_unit, check_targets_not_metres
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import solve_ik
from torchcal.kinematics.robot_checks import nominal_reach
from torchcal.stages.files import read_json_member
from torchcal.stages.store import load_model

#: A target is corrected when the model's remaining TCP position error is within this (m).
SOLVED_WITHIN_M = 1e-6
#: Targets solved per batch (bounds memory; the result does not depend on it).
BATCH = 4096
SIDECAR_SUFFIX = ".torchcal.json"
SIDECAR_FORMAT = "torchcal-compensated-program/1"


@dataclass
class ProgramOutcome:
    """What :func:`compensate_program` wrote and found."""

    out: Path
    n_targets: int
    n_corrected: int
    seconds: float
    largest_correction_deg: float
    largest_correction_joint: int
    not_corrected: list[str] = field(default_factory=list)
    tcp_note: str = ""
    allowed: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        """What the command prints: one line per target that was not corrected, then the summary."""
        summary = (f"{self.out}: {self.n_corrected} of {self.n_targets} targets corrected (the solve {self.seconds:.2f} s); "
                   f"largest joint correction {self.largest_correction_deg:.4g} deg (joint {self.largest_correction_joint}); "
                   f"{self.tcp_note}")
        allowed = [f"warning: {line} (allowed by --allow-large-corrections)" for line in self.allowed]
        return [*self.not_corrected, *allowed, summary]


def sidecar_path(out: Path) -> Path:
    return out.with_name(out.name + SIDECAR_SUFFIX)


def check_program_output(out: Path, targets: Path) -> None:
    """Refuse, before any work, an output that is the targets file or a file torchcal did not write for this.

    Raises:
        TorchcalError: one line naming the file.
    """
    if out.resolve() == targets.resolve():
        raise TorchcalError(f"{out}: --out is the targets file; give another file name")
    if out.is_dir():
        raise TorchcalError(f"{out}: --out names an existing folder; give a file name (CORRECTED.csv)")
    refuse_inside_output(out, "--out")  # the file and its record would break that folder's checksums
    if not out.exists():
        return
    side = sidecar_path(out)
    recorded = None
    if side.is_file():
        try:
            doc = read_json_member(side)
            recorded = doc.get("output_sha256") if doc.get("format") == SIDECAR_FORMAT else None
        except TorchcalError:
            recorded = None
    if recorded is None or recorded != sha256_bytes(out.read_bytes()):
        raise TorchcalError(f"{out}: exists and is not a corrected program torchcal wrote (or was changed since); "
                            "give another --out or remove it")


def read_targets(path: Path, robot) -> tuple[torch.Tensor, list[int], dict[str, list[str]]]:
    """Joint targets ``(B, N)`` rad, their file lines and the file's other columns (carried to the
    corrected file as written); bad input is one :class:`DataError` naming file, row, column."""
    table = read_csv_table(path)
    if not table.rows:
        raise DataError("no targets (only a header)", path=str(path))
    columns = joint_columns(table.header, path, robot.dof, robot.name)
    other = other_columns(table, columns, robot.dof)
    q_deg = np.stack([table.column(c) for c in columns], axis=1)
    check_joint_unit(q_deg, "deg", robot.joint_limits.numpy(), path=str(path), lines=table.line_numbers,
                     advice="a program file's joints are in degrees: convert them")
    check_joint_limits(q_deg, "deg", robot.joint_limits.numpy(), path=path, lines=table.line_numbers, columns=columns,
                       robot_name=robot.name)
    return torch.from_numpy(np.radians(q_deg)), list(table.line_numbers), other


#: A TCP pose counts as reached by the nominal inverse kinematics within this (m, rad).
IK_WITHIN = 1e-9
#: TCP pose columns of a program file (position required, orientation optional).
POSITION_COLUMNS, ROTATION_COLUMNS = ("x", "y", "z"), ("rx", "ry", "rz")


#: The corrected file's own columns after the joints (a program's other columns follow them).
OUTPUT_COLUMNS = ("corrected", "correction_deg", "remaining_mm")


def other_columns(table, used, n_joints: int) -> dict[str, list[str]]:
    """The program's columns beyond ``used`` (speed, zone, tool number...), their cells as written:
    the corrected file carries them after its own, so nothing of the program is lost. A name the
    corrected file uses itself is refused."""
    taken = {f"q{j}" for j in range(1, n_joints + 1)} | set(OUTPUT_COLUMNS)
    other = {}
    for k, name in enumerate(table.header):
        if name in used:
            continue
        if not name:
            raise DataError(f"column {k + 1} has no name: name it (the corrected file carries it by name)", path=str(table.path))
        if name in taken or name in other:
            raise DataError(f"the column name is the corrected file's own (q1..q{n_joints}, {', '.join(OUTPUT_COLUMNS)}) "
                            "or appears twice: rename it", path=str(table.path), column=name)
        other[name] = [row[k] for row in table.rows]
    return other



def is_tcp_program(path: Path) -> bool:
    """Whether the program file holds TCP poses (``x, y, z`` and no joint column) rather than joint targets."""
    header = read_csv_table(path).header
    return all(c in header for c in POSITION_COLUMNS) and not any(len(h) > 1 and h[0] == "q" and h[1:].isdigit()
                                                                   for h in header)


#: A program of at least this many TCP poses whose angles all lie within +-pi gets a warning (radians?).
RADIANS_HINT_TARGETS = 3


def read_tcp_targets(path: Path, robot, start_deg: list[float]) -> tuple[torch.Tensor, list[int], dict[str, list[str]]]:
    """Nominal joint targets ``(B, N)`` rad of a file of TCP poses, solved in order from ``start_deg``,
    their file lines and the file's other columns (:func:`other_columns`).

    ``robot``: the nominal robot ending in the production TCP (:func:`production_view`'s).
    """
    table = read_csv_table(path)
    if not table.rows:
        raise DataError("no targets (only a header)", path=str(path))
    if len(start_deg) != robot.dof or not all(math.isfinite(v) for v in start_deg):
        raise DataError(f"--start needs {robot.dof} finite joint values (deg) for {robot.name}, got {list(start_deg)}",
                        path=str(path))
    start = np.asarray(start_deg, dtype=np.float64)[None]
    check_joint_limits(start, "deg", robot.joint_limits.numpy(), path="--start", lines=[1], robot_name=robot.name)
    given = [c for c in ROTATION_COLUMNS if c in table.header]
    if given and len(given) < len(ROTATION_COLUMNS):
        missing = [c for c in ROTATION_COLUMNS if c not in table.header]
        raise DataError(f"column(s) {', '.join(given)} given without {', '.join(missing)}: a TCP orientation needs "
                        "rx, ry and rz (deg, fixed-axis XYZ); give all three, or none for positions only", path=str(path))
    oriented = len(given) == len(ROTATION_COLUMNS)
    other = other_columns(table, POSITION_COLUMNS + (ROTATION_COLUMNS if oriented else ()), robot.dof)
    position = torch.from_numpy(np.stack([table.column(c) for c in POSITION_COLUMNS], 1)) * 1e-3
    check_targets_not_metres(position, nominal_reach(robot), what="TCP target", path=str(path),
                             advice="the targets look like metres; a program file's x, y, z are in mm")
    if oriented:
        degrees = np.stack([table.column(c) for c in ROTATION_COLUMNS], 1)
        if len(degrees) >= RADIANS_HINT_TARGETS and float(np.abs(degrees).max()) <= math.pi:
            import warnings

            warnings.warn(f"{path}: every rx, ry, rz lies within +-{math.pi:.4f}: if they are radians, give them in "
                          "degrees (fixed-axis XYZ); as degrees every target's tool is within 3.2 deg of the base "
                          "axes' orientation", stacklevel=2)
        angles = torch.from_numpy(np.radians(degrees))
        targets = tf.homogeneous(tf.euler_xyz_to_matrix(angles), position)
    model = ErrorModel(robot, T_instrument_base=torch.eye(4, dtype=torch.float64))
    x = model.nominal_vector()
    q = torch.from_numpy(np.radians(start[0]))
    solved = []
    for k, line in enumerate(table.line_numbers):
        target = targets[k : k + 1] if oriented else position[k : k + 1]
        result = solve_ik(model, x, target, q[None], position_only=not oriented)
        if not bool(result.converged[0]) and not (float(result.position_error[0]) < IK_WITHIN
                                                  and float(result.rotation_error[0]) < IK_WITHIN):
            raise DataError(f"the TCP pose is not reachable by the nominal robot from the previous target's joints "
                            f"(inverse kinematics leaves {float(result.position_error[0]) * 1e3:.3g} mm, "
                            f"{math.degrees(float(result.rotation_error[0])):.3g} deg)", path=str(path), row=line)
        q = nearest_turn_within_limits(result.q[0], q, robot.joint_limits.to(torch.float64), path, line)
        solved.append(q)
    q_all = torch.stack(solved)
    for message in configuration_jumps(q_all, torch.from_numpy(np.radians(start[0])), list(table.line_numbers)):
        import warnings

        warnings.warn(f"{path}: {message}", stacklevel=2)
    return q_all, list(table.line_numbers), other


#: A joint turning further than this between consecutive targets (or from ``--start`` to the first)
#: suggests that the inverse kinematics took another arm configuration (a wrist or elbow flip).
CONFIGURATION_JUMP_DEG = 90.0


def configuration_jumps(q: torch.Tensor, start: torch.Tensor, lines: list[int]) -> list[str]:
    """One line per target whose joints ``q`` ``(B, N)`` rad turn a joint by more than
    :data:`CONFIGURATION_JUMP_DEG` from the previous target's (the first from ``start``): the program
    is meant to keep one arm configuration, and such a jump usually means it did not."""
    previous = torch.cat([start.to(q).unsqueeze(0), q[:-1]])
    moved = torch.rad2deg((q - previous).abs())
    out = []
    for k in torch.nonzero(moved.amax(-1) > CONFIGURATION_JUMP_DEG).flatten().tolist():
        j = int(moved[k].argmax())
        origin = "--start" if k == 0 else f"row {lines[k - 1]}"
        out.append(f"row {lines[k]}: joint {j + 1} turns {float(moved[k, j]):.1f} deg from {origin}: the inverse "
                   "kinematics may have taken another arm configuration (a wrist or elbow flip); check the "
                   "row's joints, or give --start in the configuration the program should keep")
    return out


def nearest_turn_within_limits(q: torch.Tensor, previous: torch.Tensor, limits: torch.Tensor, path: Path, line: int) -> torch.Tensor:
    """``q`` ``(N,)`` rad with each joint at the whole turn, within its limits, nearest ``previous``: the
    program keeps its configuration (the inverse kinematics may end a joint a turn away: 470 deg for
    110 deg outside the limits, or -330 deg for 30 deg inside them).

    Raises:
        DataError: naming the row (the pose) and the joint that no whole turn brings inside its limits.
    """
    turn = 2.0 * math.pi
    out = q.clone()
    tol = math.radians(0.01)  # as the limit check of measurement files
    for j in range(len(q)):
        low, high = float(limits[j, 0]), float(limits[j, 1])
        value = float(q[j])
        if not (math.isfinite(low) and math.isfinite(high)):  # a continuous joint: the turn nearest the previous value
            out[j] = value + round((float(previous[j]) - value) / turn) * turn
            continue
        options = [value + k * turn for k in range(math.ceil((low - tol - value) / turn), math.floor((high + tol - value) / turn) + 1)]
        if not options:
            raise DataError(f"the inverse kinematics from the previous target's joints ends with joint {j + 1} at "
                            f"{math.degrees(value):.6g} deg, outside its limits [{math.degrees(low):.6g}, "
                            f"{math.degrees(high):.6g}] deg at every whole turn: give a start nearer this pose's "
                            "configuration (or a program that reaches it in smaller steps)", path=str(path), row=line)
        out[j] = min(options, key=lambda v: abs(v - float(previous[j])))
    return out


def _csv(q_deg: np.ndarray, corrected: np.ndarray, correction_deg: np.ndarray, remaining_mm: np.ndarray,
         other: dict[str, list[str]] | None = None) -> str:
    """The corrected program: ``q1..qN`` (deg), :data:`OUTPUT_COLUMNS`, then the program's other columns as written."""
    other = other or {}
    n = q_deg.shape[1]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow([f"q{j}" for j in range(1, n + 1)] + list(OUTPUT_COLUMNS) + list(other))
    for k, (row, ok, move, rest) in enumerate(zip(q_deg, corrected, correction_deg, remaining_mm)):
        writer.writerow([repr(float(v)) for v in row] + [str(int(ok)), f"{move:.6g}", f"{rest:.6g}"]
                        + [cells[k] for cells in other.values()])
    return buffer.getvalue()


def compensate_program(
    model_dir: str | Path,
    targets: str | Path,
    out: str | Path,
    *,
    task: str = DEFAULT_TASK,
    iterations: int | None = None,
    tcp_mm: list[float] | None = None,
    tcp_rpy_deg: list[float] | None = None,
    allow_large_corrections: bool = False,
    start_deg: list[float] | None = None,
    tool_length_mm: float = 0.0,
) -> ProgramOutcome:
    """Correct the joint targets of ``targets`` with the compensator of ``model_dir`` into ``out``.

    ``task``, ``iterations``, ``tcp_mm``, ``tcp_rpy_deg``, ``tool_length_mm``: as ``torchcal export`` (the same
    compensator; without a TCP, the flange, stated in the summary). ``start_deg``: the start
    configuration of a file of TCP poses (module docstring); refused with joint targets.
    """
    model_dir, targets, out = Path(model_dir), Path(targets), Path(out)
    if task not in TASKS:
        raise TorchcalError(f"task must be one of {list(TASKS)}, got {task!r}")
    if iterations is not None and not 1 <= iterations <= MAX_ITERATIONS:  # the export's bound: the same compensator
        raise TorchcalError(f"--iterations must be in [1, {MAX_ITERATIONS}] (as for export), got {iterations}")
    check_tool_length(tool_length_mm)
    check_program_output(out, targets)
    stored = load_model(model_dir)
    stored = production_view(stored, tcp_transform(tcp_mm, tcp_rpy_deg))  # as export: the flange by default
    tcp_note = (f"targets of the TCP {tcp_mm or [0, 0, 0]} mm, {tcp_rpy_deg or [0, 0, 0]} deg in the flange frame"
                + ("" if tcp_mm or tcp_rpy_deg else " (the flange; --tcp-mm sets the production TCP)"))
    if is_tcp_program(targets):
        if start_deg is None:
            raise DataError("TCP poses (x, y, z) need a start configuration: give --start q1 .. qN (deg)", path=str(targets))
        q, lines, other = read_tcp_targets(targets, stored.robot, start_deg)
    else:
        if start_deg is not None:
            raise DataError("--start is for a file of TCP poses (x, y, z); this one holds joint targets", path=str(targets))
        q, lines, other = read_targets(targets, stored.robot)
    graphs = build_graphs(stored, task=task, iterations=iterations, tool_length=tool_length_mm * 1e-3)
    if has_wrench_input(graphs):
        raise TorchcalError(f"{model_dir}: the model has a stiffness stage, whose compensator needs each target's "
                            "expected wrench; compensate a program with the geometric model, or use the exported graphs")
    graph = compensator_of(graphs)
    extent = {}  # the export's check, on the poses it judges (training poses less the singular ones: _regular)
    if stored.training_q is not None and len(regular_poses(stored.robot, stored.training_q)):
        extent["training poses"] = correction_extent(graph, regular_poses(stored.robot, stored.training_q))
    allowed = check_corrections(extent, allow_large_corrections, command="compensate")
    start = time.perf_counter()
    q_c, residual = [], []
    with torch.no_grad():
        for chunk in torch.split(q, BATCH):
            a, b = graph.solve(chunk.to(torch.float64))
            q_c.append(a)
            residual.append(b)
    seconds = time.perf_counter() - start
    # the compensator's own command everywhere (the exported runtime's): it returns the nominal one
    # itself where its steps end further off; a command that is better but not solved to 1 um is kept
    written, rest = torch.cat(q_c), torch.cat(residual)
    corrected = rest[:, 0] <= SOLVED_WITHIN_M
    remaining_mm = rest[:, 0] * 1e3  # the model's remaining error at the written command (the graph's residual)
    kept = (written == q).all(-1)
    unsolved = torch.nonzero(~corrected).flatten().tolist()
    if unsolved:
        with torch.no_grad():
            nominal_mm = graphs["monitor"](q[unsolved]).norm(dim=-1) * 1e3
    failures = []
    for i, k in enumerate(unsolved):
        if bool(kept[k]):
            failures.append(f"{targets}: row {lines[k]}: not corrected, nominal command kept ({float(nominal_mm[i]):.3g} mm "
                            "off by the model): the compensator's steps ended further off (beyond reach, a joint limit "
                            "or a singularity)")
        else:
            failures.append(f"{targets}: row {lines[k]}: not solved to {SOLVED_WITHIN_M * 1e3:g} mm: the compensator's "
                            f"command, written, leaves the model's TCP {float(remaining_mm[k]):.3g} mm off the target "
                            f"(the nominal command {float(nominal_mm[i]):.3g} mm)")
    applied = (written - q).abs()
    worst = int(applied.amax(0).argmax()) if len(q) else 0
    text = _csv(np.degrees(written.numpy()), corrected.numpy(), np.degrees(applied.amax(-1).numpy()),
                remaining_mm.numpy(), other)
    outcome = ProgramOutcome(out=out, n_targets=len(q), n_corrected=int(corrected.sum()), seconds=seconds,
                             largest_correction_deg=math.degrees(float(applied.max())) if len(q) else 0.0,
                             largest_correction_joint=worst + 1, not_corrected=failures, tcp_note=tcp_note,
                             allowed=allowed)
    atomic_write_text(out, text)
    atomic_write_json(sidecar_path(out), {
        "format": SIDECAR_FORMAT,
        "model": str(model_dir), "model_checksums_sha256": sha256_bytes((model_dir / "checksums.json").read_bytes()),
        "targets": str(targets), "targets_sha256": sha256_bytes(targets.read_bytes()),
        "output_sha256": sha256_bytes(text.encode()),
        "task": graph.task, "iterations": graph.iterations, "tcp": tcp_note,
        "limits": {"solved_within_mm": SOLVED_WITHIN_M * 1e3}, "corrections": {"extent": extent, "exceeded_but_allowed": allowed},
        "n_targets": outcome.n_targets, "n_corrected": outcome.n_corrected,
        "largest_correction_deg": outcome.largest_correction_deg, "seconds": seconds,
    })
    return outcome
