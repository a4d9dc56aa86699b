"""The TCP the compensator serves, and how far its corrections reach.

A calibration measures a reflector (or probe) on the flange; production needs another point: the
torch tip, the gripper centre. :func:`production_view` re-expresses a stored model so that both the
nominal and the calibrated chain end in the production TCP ``T_flange_tcp`` (position in mm and
fixed-axis XYZ angles in deg, in the ``flange`` frame; default: the flange itself): the flange
frame ``T_N_flange`` becomes ``T_N_flange T_flange_tcp`` and the tool entries are zero. The
compensator then corrects where the calibrated model puts *that* point (and its orientation),
using the flange orientation the model knows, not the measuring reflector's fitted offset.

:func:`correction_extent` measures the largest joint correction and the largest orientation
deviation of the tool that the compensator's commands leave, over the training poses and over
the joint range; :func:`check_corrections` refuses an export whose median over the training
poses exceeds :data:`MAX_JOINT_CORRECTION_DEG` or :data:`MAX_TOOL_ROTATION_DEG` unless the user allows it explicitly: corrections that large
come from parameters the data did not determine, or from a wrong robot file.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from torchcal.core.errors import TorchcalError
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel

#: An export whose joint corrections exceed this (deg; median over the training poses: the largest and
#: the 99th percentile are reported, over the joint range too, but near singular poses any step is
#: large, so they are not judged) is refused without ``allow_large_corrections``.
MAX_JOINT_CORRECTION_DEG = 2.0
#: An export whose tool orientation deviation exceeds this (deg, median as above) is refused likewise.
MAX_TOOL_ROTATION_DEG = 2.0


#: A production TCP farther than this from the flange (mm) is refused: no tool is that long (a unit mistake).
MAX_TCP_OFFSET_MM = 3000.0


def tcp_transform(position_mm: list[float] | None, rpy_deg: list[float] | None) -> torch.Tensor:
    """``T_flange_tcp`` ``(4, 4)`` (m) from a position (mm) and fixed-axis XYZ angles (deg)."""
    position = [0.0, 0.0, 0.0] if position_mm is None else [float(v) for v in position_mm]
    angles = [0.0, 0.0, 0.0] if rpy_deg is None else [float(v) for v in rpy_deg]
    if len(position) != 3 or len(angles) != 3 or not all(math.isfinite(v) for v in position + angles):
        raise TorchcalError(f"the production TCP needs 3 finite position values (mm) and 3 angles (deg), "
                            f"got {position} and {angles}")
    offset = math.hypot(*position)
    if offset > MAX_TCP_OFFSET_MM:
        raise TorchcalError(f"the production TCP lies {offset:.6g} mm from the flange (--tcp-mm {position}); tools reach at "
                            f"most {MAX_TCP_OFFSET_MM:g} mm: give it in mm, in the flange frame")
    rotation = tf.euler_xyz_to_matrix(torch.tensor([math.radians(a) for a in angles], dtype=torch.float64))
    return tf.homogeneous(rotation, torch.tensor(position, dtype=torch.float64) * 1e-3)


def production_view(stored, T_flange_tcp: torch.Tensor):
    """``stored`` with both chains ending in the production TCP (the fitted tool entries set to zero).

    A gravity-compliance term at the ``tcp`` point keeps the point it was fitted at (the payload of
    the calibration): its torques do not follow the production TCP.
    """
    robot = replace(stored.robot, T_n_flange=stored.robot.T_n_flange.to(torch.float64) @ T_flange_tcp,
                    tool=torch.zeros(3, dtype=torch.float64))
    model = ErrorModel(robot, with_orientation=stored.model.with_orientation,
                       parallel_threshold_deg=stored.model.parallel_threshold_deg,
                       T_instrument_base=stored.model.T_reference, device=stored.model.device)
    x = stored.x.clone()
    x[model.layout.tool_slice] = 0.0
    metadata = stored.metadata
    terms = JointSpaceErrors.from_metadata(metadata)
    if terms.compliance is not None:
        compliance = terms.compliance
        fitted = stored.robot.tool.to(torch.float64) if compliance.tcp_point is None else compliance.tcp_point
        rotation, shift = T_flange_tcp[:3, :3].to(torch.float64), T_flange_tcp[:3, 3].to(torch.float64)
        pinned = replace(compliance, tcp_point=rotation.T @ (fitted - shift))  # in the new flange frame
        metadata = {**metadata, **JointSpaceErrors(pinned, terms.harmonics).to_metadata()}
    return replace(stored, robot=robot, model=model, x=x, metadata=metadata)


def tcp_entry(T_flange_tcp: torch.Tensor, position_mm, rpy_deg, stored) -> dict:
    """The manifest's ``tcp``: what the compensator targets (default: the flange), and the measured point it does not."""
    layout = stored.model.layout
    reflector = (stored.x[layout.tool_slice][:3].detach().cpu() * 1e3).tolist()
    return {
        "position_mm": (T_flange_tcp[:3, 3] * 1e3).tolist(),
        "rpy_deg": [0.0, 0.0, 0.0] if rpy_deg is None else [float(v) for v in rpy_deg],
        "frame": "flange",
        "is_flange": position_mm is None and rpy_deg is None,
        "measured_point_mm": reflector,
        "note": ("the compensator moves this TCP (position and orientation) to where the nominal robot puts it; the "
                 "measured point (the calibration's reflector or probe) is not its target; export --tcp-mm / "
                 "--tcp-rpy-deg give another TCP"),
    }


def correction_extent(graph, q: torch.Tensor, stored=None) -> dict:
    """Largest joint correction (deg, and which joint) and tool orientation deviation (deg) of ``graph``'s commands at ``q``.

    With ``stored`` (the model ``graph`` was built from) also the corrections' 1-sigma from the
    calibration's uncertainty (:func:`correction_sigma`): at the largest correction, and per joint
    the median over at most :data:`SIGMA_POSES` of the poses.
    """
    q = q.to(torch.float64)
    with torch.no_grad():
        q_c, residual = graph.solve(q)
    move = (q_c - q).abs()
    pose, worst = divmod(int(move.argmax()), move.shape[1])
    per_pose = move.amax(-1)
    extent = {
        "n_poses": int(q.shape[0]),
        "largest_joint_correction_deg": math.degrees(float(move.max())),
        "joint": worst + 1,
        "p99_joint_correction_deg": math.degrees(float(per_pose.quantile(0.99))),
        "median_joint_correction_deg": math.degrees(float(per_pose.median())),
        "largest_tool_rotation_deg": math.degrees(float(residual[:, 1].max())),
        "p99_tool_rotation_deg": math.degrees(float(residual[:, 1].quantile(0.99))),
        "median_tool_rotation_deg": math.degrees(float(residual[:, 1].median())),
    }
    if stored is not None:
        # the largest correction's pose first, then an even spread of the others
        sample = torch.cat([torch.tensor([pose]), torch.linspace(0, len(q) - 1, min(SIGMA_POSES, len(q)) - 1).long()])
        sigma = correction_sigma(stored, graph, q[sample])
        extent["largest_joint_correction_sigma_deg"] = _degrees_or_none(sigma[0, worst])
        extent["median_joint_correction_sigma_deg"] = [_degrees_or_none(v) for v in sigma.median(0).values]
        notes = [SIGMA_FROM] + ([] if stored.metadata.get("prior") else [RANK_CUT_NOTE])
        if stored.joint_covariance is None and not JointSpaceErrors.from_metadata(stored.metadata).empty:
            notes.append(NO_JOINT_COVARIANCE_NOTE)
        extent["sigma_from"] = "; ".join(notes)
    return extent


def _degrees_or_none(value: torch.Tensor) -> float | None:
    """Degrees of a rad value; ``None`` (JSON null) where the fit stated no uncertainty (NaN)."""
    degrees = math.degrees(float(value))
    return degrees if math.isfinite(degrees) else None


#: Poses at which :func:`correction_extent` computes the corrections' sigma (one solve per table parameter).
SIGMA_POSES = 50
SIGMA_FROM = ("the posterior covariance of the calibrated MDH table and of the joint-space terms' coefficients given the "
              "robot base frame (the compensator's frame: what only moves that frame is not an error of the robot in it; "
              "the measuring tool does not enter), propagated through the compensator's solve (finite differences)")
NO_JOINT_COVARIANCE_NOTE = ("the model's joint-space terms carry no covariance (a model written by an update or an older "
                            "version): their own uncertainty is not included, so this sigma is a lower bound")
RANK_CUT_NOTE = ("a fit without a prior (prior=none): the parameters its rank cut fixed at nominal count as exact, "
                 "so this sigma is a lower bound")


DIFFERENCE_TOLERANCE = (1e-10, 1e-10)
"""Convergence tolerances (m, rad) of the commands :func:`correction_sigma` differences: tighter than
the exported graph's, so that where a pose stops does not enter the difference (the orientation's
1e-7 rad would add about 1e-5 rad per column at ``step`` 0.01)."""


def correction_sigma(stored, graph, q: torch.Tensor, step: float = 0.01) -> torch.Tensor:
    """1-sigma ``(n, N)`` (rad) of each joint correction of ``graph``'s commands at ``q`` ``(n, N)`` rad.

    The covariance is that of the MDH table's parameters and of the joint-space terms' coefficients
    (where the fit stored their joint covariance, :attr:`StoredModel.joint_covariance`) given the
    robot base frame's (Gaussian conditioning): the compensator works in that frame, so a table
    parameter that only moves it (``theta1`` with the frame's rotation about z) is no uncertainty of
    a command, while one the data did not see (``theta6``: the flange's roll) carries its prior's
    sigma into the corrections it drives. The solved command is differenced (forward, ``step``
    sigma: the steps converge to :data:`DIFFERENCE_TOLERANCE`, far below ``step`` times a correction's sensitivity) along
    each column of a square root of that covariance (eigen-decomposition ``C = R R^T``), with the
    graph's own task and steps; the variances of the columns add. (With a ``tool_length`` a pose at
    the switch between its corrected and its nominal command differences across the switch: its
    sigma there is the jump's, an upper bound.)
    """
    layout = stored.model.layout
    free = stored.free.tolist()
    table_rows = [k for k, i in enumerate(free) if layout.table_slice.start <= i < layout.table_slice.stop]
    covariance, coefficients = stored.covariance, torch.zeros(0, 2, dtype=torch.long)
    if stored.joint_covariance is not None and stored.joint_coefficients is not None:
        covariance, coefficients = stored.joint_covariance, stored.joint_coefficients
    rows = table_rows + [len(free) + k for k in range(len(coefficients))]
    if not rows:
        return torch.zeros(q.shape, dtype=torch.float64)
    frame = [k for k, i in enumerate(free) if layout.base_slice.start <= i < layout.base_slice.stop]
    index = stored.free[table_rows]
    terms = JointSpaceErrors.from_metadata(stored.metadata)
    covariance = covariance.to(torch.float64)
    if not bool(torch.isfinite(covariance).all()):  # a fit that could not state its uncertainty claims none here
        return torch.full(q.shape, float("nan"), dtype=torch.float64)
    table = covariance[rows][:, rows]
    if frame:
        cross = covariance[rows][:, frame]
        table = table - cross @ torch.linalg.pinv(covariance[frame][:, frame], hermitian=True) @ cross.T
    values, vectors = torch.linalg.eigh(0.5 * (table + table.T))
    root = vectors * values.clamp_min(0.0).sqrt()
    variance = torch.zeros(q.shape, dtype=torch.float64)

    def solved(shift: torch.Tensor | None) -> torch.Tensor:
        changed = stored
        if shift is not None:  # the table's parameters, then the coefficients, moved by ``shift``
            x = stored.x.clone()
            x[index] += shift[: len(table_rows)].to(x)
            metadata = stored.metadata
            if len(coefficients):
                metadata = {**metadata, **terms.shifted(coefficients, shift[len(table_rows):]).to_metadata()}
            changed = replace(stored, x=x, metadata=metadata)
        return type(graph).from_stored(changed, task=graph.task, iterations=graph.iterations, tool_length=graph.tool_length,
                                       orientation_source=graph.orientation_source,
                                       converged_position_m=DIFFERENCE_TOLERANCE[0],
                                       converged_orientation_rad=DIFFERENCE_TOLERANCE[1]).solve(q)[0]

    with torch.no_grad():
        at_fit = solved(None)
        for column in root.T:
            if float(column.abs().max()) == 0.0:
                continue
            variance += ((solved(step * column) - at_fit) / step) ** 2
    return variance.sqrt()


def check_corrections(extent: dict[str, dict], allow: bool, command: str = "export") -> list[str]:
    """Lines naming the limits an export exceeds; raises :class:`TorchcalError` unless ``allow``
    (``command``: the command that refuses, ``export`` or ``compensate``)."""
    found = []
    # the training poses are judged; a model without them (a tracer fit keeps none) by the joint range.
    # The other sets are reported, not judged: near (not at) singular poses any orientation step is large
    judged = "training poses" if "training poses" in extent else "joint range"
    for where, e in extent.items():
        if where != judged:
            continue
        if e["median_joint_correction_deg"] > MAX_JOINT_CORRECTION_DEG:
            found.append(f"joint corrections of {e['median_joint_correction_deg']:.3g} deg (median; up to "
                         f"{e['largest_joint_correction_deg']:.3g}, joint {e['joint']}) over the {where} "
                         f"(limit {MAX_JOINT_CORRECTION_DEG:g} deg)")
        if e["median_tool_rotation_deg"] > MAX_TOOL_ROTATION_DEG:
            found.append(f"tool orientation off by {e['median_tool_rotation_deg']:.3g} deg (median; up to "
                         f"{e['largest_tool_rotation_deg']:.3g}) over the {where} (limit {MAX_TOOL_ROTATION_DEG:g} deg)")
    if found and not allow:
        raise TorchcalError(f"{command} refused: " + "; ".join(found) + ". Corrections this large come from parameters the "
                            "data did not determine or from a wrong robot file; check the calibration's prior report, or "
                            "pass --allow-large-corrections to export anyway")
    return found
