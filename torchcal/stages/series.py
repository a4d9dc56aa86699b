"""One fit over several measurement series of one robot, each series with its own frame (and tool).

A series is one instrument placement: a tracker moved between two campaigns measures the same
robot in another frame, and a probe re-mounted sits at another point of the flange. The fit
estimates what the series share (the robot's geometry and joint-space terms, the first series'
instrument frame, the tool unless ``series_tool=per_series``) together with what each series has
alone (``T_series_reference``: the first series' instrument frame into this series' frame; with
``per_series`` a tool offset in the TCP frame).

How: block-coordinate descent on the one least-squares cost. Given the robot model, each
series' frame (and tool offset) is registered in closed form (Kabsch; the tool offset is the
mean of the residuals rotated into the TCP frame, alternated with Kabsch); given the frames,
every series' points are mapped into the first series' frame and the pooled set is fitted as
one file. Each step lowers the cost; the steps repeat until the mapped points move less than
:data:`TOLERANCE_MM`. The structure (joint-space terms) is chosen once, by the grouped CV of the
pooled set with folds made within each series (:func:`torchcal.data.folds.series_folds`); the
alternation first runs with the geometry alone, then with the chosen structure.

The frames are nuisance parameters of the set-ups: the model folder keeps them
(``calibration.json`` ``series``) with each file's hash and row count, predicts in the first
series' frame, and scoring another series re-registers the frame as for any file. The exported
compensator holds the robot alone (geometry and joint terms), as for one series.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from torchcal.config.schema import FitConfig
from torchcal.core.errors import DataError
from torchcal.data.measurements import Measurements
from torchcal.data.series import pool_series
from torchcal.identify.calibrate import CalibrationResult
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.kinematics.robot import RobotModel
from torchcal.kinematics.transforms import rigid_registration
from torchcal.model_selection.structure import StructureCV
from torchcal.stages.geometry import fit_with_selection, nominal_fit

#: ``series_tool`` values: one tool for every series, or a tool offset per series (mounts differ).
SERIES_TOOLS = ("auto", "shared", "per_series")
#: ``series_frame`` values: a frame per series (the tracker moved), or one frame (it stayed).
SERIES_FRAMES = ("auto", "per_series", "shared")
#: ``auto``: series whose frames, fitted with the nominal robot, move their points less than this
#: (RMS, mm) share one frame. The nominal robot's own error leaves ~2 mm between series measured
#: from one placement (UR10 B and C: 1.75 mm); a moved tracker differs by metres (UR10 A, C, D: 1-3.7 m).
FRAME_AGREEMENT_MM = 10.0
#: ``auto``: tools fitted with the nominal robot that differ by less than this (mm) are one tool
#: (UR10 B and C: 0.31 mm apart; D's re-mounted probe: 38 mm from the others).
TOOL_AGREEMENT_MM = 5.0
#: The alternation stops when no series' mapped points move more than this (RMS, mm).
TOLERANCE_MM = 1e-3
#: Alternations at most: with the geometry alone, then with the chosen structure.
MAX_GEOMETRY_ROUNDS, MAX_STRUCTURE_ROUNDS = 16, 6


@dataclass
class SeriesFrame:
    """One series' set-up in a pooled fit.

    Attributes:
        transform: ``(4, 4)`` ``T_series_reference``: points of the reference (first series')
            instrument frame into this series' instrument frame (m); the identity for the first.
        tool_offset: ``(3,)`` m, this series' TCP minus the model's, in the TCP frame (zeros when
            the tool is shared and for the first series).
    """

    transform: torch.Tensor
    tool_offset: torch.Tensor


@dataclass
class SeriesFit:
    """What :func:`fit_series` produced: the fit on the pooled set, its structure CV, the pooled
    set in the reference frame (what the model folder and the residual stage see), the frames,
    and the alternation's record (rounds, last movement)."""

    result: CalibrationResult
    structure: StructureCV | None
    pooled: Measurements
    frames: list[SeriesFrame]
    rounds: int
    last_move_mm: float
    tool: str = "shared"


def _tcp_in_reference(result, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """TCP positions ``(n, 3)`` and rotations ``(n, 3, 3)`` of a fit in its instrument frame."""
    joints = JointSpaceErrors.of(result).effective_joints(result.model.robot, q.to(result.x.device))
    pose = result.model.tcp_pose(joints, result.x)
    return pose[..., :3, 3].cpu(), pose[..., :3, :3].cpu()


def _nominal_in_reference(robot: RobotModel, reference: torch.Tensor, q: torch.Tensor):
    """The nominal robot's TCP positions and rotations in a frame ``reference`` (``T_frame_base``)."""
    pose = reference @ robot.flange_pose(q)
    return pose[..., :3, :3] @ robot.tool.to(q) + pose[..., :3, 3], pose[..., :3, :3]


def map_to_reference(data: Measurements, frame: SeriesFrame, rotation: torch.Tensor) -> Measurements:
    """``data`` (one series) in the reference frame, its tool offset removed (``rotation``: the TCP's, reference frame)."""
    r, t = frame.transform[:3, :3], frame.transform[:3, 3]
    position = (data.position - t) @ r - rotation @ frame.tool_offset
    measured_rotation = None if data.rotation is None else r.T @ data.rotation
    return replace(data, position=position, rotation=measured_rotation)


def register_series(predicted: torch.Tensor, rotation: torch.Tensor, data: Measurements, per_series_tool: bool,
                    iterations: int = 50) -> SeriesFrame:
    """The frame (and tool offset) of one series against a model's TCP ``predicted`` ``(n, 3)`` and
    ``rotation`` ``(n, 3, 3)`` in the reference frame: the least-squares optimum for that model."""
    offset = torch.zeros(3, dtype=predicted.dtype)
    for _ in range(iterations if per_series_tool else 1):
        transform = rigid_registration(predicted + rotation @ offset, data.position)
        if not per_series_tool:
            break
        back = (data.position - transform[:3, 3]) @ transform[:3, :3]
        new = (rotation.transpose(-1, -2) @ (back - predicted).unsqueeze(-1)).squeeze(-1).mean(0)
        done = float((new - offset).norm()) < 1e-10
        offset = new
        if done:
            break
    return SeriesFrame(transform, offset)


def _nominal_fits(robot: RobotModel, series: list[Measurements]) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """:func:`~torchcal.stages.geometry.nominal_fit` of each series (frame and tool fitted, positions only)."""
    return [nominal_fit(robot, s) for s in series]


def _initial_frames(robot: RobotModel, series: list[Measurements], per_series_tool: bool, fits=None):
    """Frames from the nominal robot with frame and tool fitted to each series (the first is the reference);
    ``fits``: the series' :func:`_nominal_fits` where already computed."""
    fits = _nominal_fits(robot, series) if fits is None else fits
    _, t0, tool0 = fits[0]
    frames = [SeriesFrame(t @ torch.linalg.inv(t0), (tool - tool0) if per_series_tool else torch.zeros(3, dtype=tool.dtype))
              for _, t, tool in fits]
    frames[0] = SeriesFrame(torch.eye(4, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    rotations = [_nominal_in_reference(robot, t0, s.q)[1] for s in series]
    return frames, rotations


def _pool(series: list[Measurements], frames: list[SeriesFrame], rotations: list[torch.Tensor]) -> Measurements:
    pooled = pool_series([map_to_reference(s, f, r) for s, f, r in zip(series, frames, rotations)])
    return replace(pooled, source=" + ".join(s.source for s in series))


def _reregister(result, series: list[Measurements], frames: list[SeriesFrame], per_series_tool: bool):
    """New frames for the model ``result``; returns them, the TCP rotations and how far the mapped points moved (mm)."""
    new, rotations, moved = [frames[0]], [], 0.0
    for k, s in enumerate(series):
        predicted, rotation = _tcp_in_reference(result, s.q)
        rotations.append(rotation)
        if k == 0:
            continue
        frame = register_series(predicted, rotation, s, per_series_tool)
        before = map_to_reference(s, frames[k], rotation).position
        after = map_to_reference(s, frame, rotation).position
        moved = max(moved, _rms_mm(after - before))
        new.append(frame)
    return new, rotations, moved


def fit_series(robot: RobotModel, series: list[Measurements], config: FitConfig, *, progress=None) -> SeriesFit:
    """Fit ``robot`` to several series at once (see the module docstring); ``config.series_tool`` says
    whether the tool is shared or each series has its own offset.

    Every solve registers each series' frame at its optimum (variable projection,
    :mod:`torchcal.identify.series_frames`). The points are mapped into the first series' frame
    (where the cross-validation scores them) by frames from the nominal robot, then from a fit of
    the geometry alone, then (recorded, for the model folder) from the final fit. A per-series tool
    offset is not projected: it alternates with the fit until the mapped points move less than
    :data:`TOLERANCE_MM`.
    """
    if len(series) < 2:
        raise DataError("a fit over several series needs at least two measurement files")
    # the nominal fits decide ``auto`` and start the frames: computed once for both
    fits = _nominal_fits(robot, series) if "auto" in (config.series_frame, config.series_tool) else None
    frame_mode, tool_mode, why = resolve_set_ups(robot, series, config, fits)
    config = replace(config, series_frame=frame_mode, series_tool=tool_mode)
    if config.series_frame == "shared":
        fit = _fit_shared_frame(robot, series, config, progress)
        if why:
            fit.result.notes.append(why)
        return fit
    # the frames are registered on points: orientation columns would need a rotation per series too
    series = [replace(s, rotation=None) for s in series]
    per_tool = config.series_tool == "per_series"
    frames, rotations = _initial_frames(robot, series, per_tool, fits)
    quiet = replace(config, residual="none", uncertainty="none", progress=False)
    geometry_only = replace(quiet, gravity_compliance="none", joint_harmonics="none")
    rounds, moved = 0, float("inf")
    for _ in range(MAX_GEOMETRY_ROUNDS if per_tool else 1):
        if progress is not None:
            progress(f"registering {len(series)} series: round {rounds + 1} (geometry)")
        result = fit_with_selection(robot, _pool(series, frames, rotations), geometry_only)[0]
        frames, rotations, moved = _reregister(result, series, frames, per_tool)
        rounds += 1
        if moved < TOLERANCE_MM:
            break
    pooled = _pool(series, frames, rotations)
    result, structure = fit_with_selection(robot, pooled, config, progress=progress)
    frames, rotations, moved = _reregister(result, series, frames, per_tool)
    rounds += 1
    if per_tool and structure is not None and moved >= TOLERANCE_MM:
        gravity, harmonics = structure.chosen
        chosen = replace(quiet, gravity_compliance=gravity, joint_harmonics=harmonics)
        notes = [n for n in result.notes if n.startswith("structure chosen")]
        for _ in range(MAX_STRUCTURE_ROUNDS):
            if progress is not None:
                progress(f"registering {len(series)} series: round {rounds + 1} ({gravity}, {harmonics})")
            result = fit_with_selection(robot, _pool(series, frames, rotations), chosen)[0]
            result.notes.extend(notes)
            frames, rotations, moved = _reregister(result, series, frames, per_tool)
            rounds += 1
            if moved < TOLERANCE_MM:
                break
    # with one tool the fit does not depend on how the later series were mapped (their frames are projected)
    pooled = _pool(series, frames, rotations)
    result.notes.append(f"{len(series)} measurement series fitted together, each with its own instrument frame"
                        + (" and tool offset" if per_tool else " (one tool)")
                        + f"; mapped into the first series' frame by the fit's frames ({rounds} registrations, "
                        f"the last moved the points {moved:.4f} mm RMS)")
    if why:
        result.notes.append(why)
    return SeriesFit(result, structure, pooled, frames, rounds, moved, config.series_tool)


def resolve_set_ups(robot: RobotModel, series: list[Measurements], config: FitConfig,
                    fits=None) -> tuple[str, str, str]:
    """``(series_frame, series_tool, note)`` with ``auto`` resolved from each series' nominal fit (frame and tool).

    One frame where every series' frame moves its points less than :data:`FRAME_AGREEMENT_MM`
    from the first's and the tools agree within :data:`TOOL_AGREEMENT_MM`; one tool where the
    tools agree. Why: a frame per series leaves the fit free to turn one series against another,
    which a tracker that stayed does not (UR10 B and C together scored on series A: one frame
    0.4637 mm, a frame each 0.4726, ``docs/multi_series_real.md``). The note says what was found.
    ``fits``: the series' :func:`_nominal_fits` where already computed.
    """
    frame_mode, tool_mode = config.series_frame, config.series_tool
    if frame_mode not in SERIES_FRAMES:
        raise DataError(f"unknown series_frame '{frame_mode}'; choose one of {', '.join(SERIES_FRAMES)}")
    if tool_mode not in SERIES_TOOLS:
        raise DataError(f"unknown series_tool '{tool_mode}'; choose one of {', '.join(SERIES_TOOLS)}")
    if "auto" not in (frame_mode, tool_mode):
        return frame_mode, tool_mode, ""
    fits = _nominal_fits(robot, series) if fits is None else fits
    _, t0, tool0 = fits[0]
    frame_mm = max(_rms_mm((s.position @ rel[:3, :3].T + rel[:3, 3]) - s.position)
                   for s, rel in ((s, t0 @ torch.linalg.inv(t)) for s, (_, t, _) in zip(series[1:], fits[1:])))
    tool_mm = max(float((tool - tool0).norm()) * 1e3 for _, _, tool in fits[1:])
    if tool_mode == "auto":
        tool_mode = "shared" if tool_mm < TOOL_AGREEMENT_MM else "per_series"
    if frame_mode == "auto":
        frame_mode = "shared" if frame_mm < FRAME_AGREEMENT_MM and tool_mode == "shared" else "per_series"
    note = (f"set-ups (auto): the series' frames fitted with the nominal robot differ by up to {frame_mm:.1f} mm "
            f"at their points (one frame below {FRAME_AGREEMENT_MM:g}), their tools by up to {tool_mm:.1f} mm (one "
            f"tool below {TOOL_AGREEMENT_MM:g}): series_frame={frame_mode}, series_tool={tool_mode}")
    return frame_mode, tool_mode, note


def _rms_mm(errors: torch.Tensor) -> float:
    return float(errors.norm(dim=-1).pow(2).mean().sqrt()) * 1e3


def _fit_shared_frame(robot: RobotModel, series: list[Measurements], config: FitConfig, progress) -> SeriesFit:
    """Series measured from one instrument placement with one tool: the pooled set is one set-up.

    The folds are made over the pooled set (its regions may hold poses of several series: they
    share the frame); blocks of measurement order follow the files one after the other.
    """
    if config.series_tool != "shared":
        raise DataError("series_frame=shared takes one tool too (series_tool=shared): a re-mounted probe is "
                        "another set-up, give it its own frame")
    lines = [line + k * 10**7 for k, s in enumerate(series) for line in s.line_numbers]
    in_files = pool_series(series)
    pooled = replace(in_files, series=None, line_numbers=tuple(lines))
    result, structure = fit_with_selection(robot, pooled, config, progress=progress)
    result.notes.append(f"{len(series)} measurement series fitted together in one instrument frame with one tool")
    identity = SeriesFrame(torch.eye(4, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    return SeriesFit(result, structure, replace(pooled, line_numbers=in_files.line_numbers),
                     [identity] * len(series), 0, 0.0, "shared")


def series_metadata(series: list[Measurements], fit: SeriesFit) -> dict:
    """The ``series`` entry of ``calibration.json``: each file, its hash, rows, frame and tool offset, its RMS."""
    entries, start = [], 0
    for s, frame in zip(series, fit.frames):
        part = fit.pooled.subset(torch.arange(start, start + len(s)))
        start += len(s)
        predicted = _tcp_in_reference(fit.result, part.q)[0]
        rms = _rms_mm(part.position - predicted)
        entries.append({"file": s.source, "sha256": s.sha256, "n_poses": len(s),
                        "T_series_reference": frame.transform.tolist(),
                        "tool_offset_mm": (frame.tool_offset * 1e3).tolist(), "fit_rms_mm": rms})
    return {"series": {"frames": "T_series_reference maps the model's instrument frame (the first series') into "
                                 "each series' instrument frame, m", "tool": fit.tool,
                       "frame": "shared" if fit.rounds == 0 else "per_series",
                       "rounds": fit.rounds, "last_move_mm": fit.last_move_mm, "files": entries}}
