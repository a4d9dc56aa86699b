"""``torchcal motion``: a joint trajectory for a waypoint path, with its report.

Reads the path file (:mod:`torchcal.motion.waypoints`), the robot file and, with a model folder,
the calibrated kinematics (geometry and joint-space errors: the joints the real robot must be
sent); plans the motion (:mod:`torchcal.motion.planner`); writes the report (always) and the
trajectory CSV (``t`` s, ``q1..qN`` deg, one row every ``dt``; atomically) when every sample is
within the path tolerance and the joint limits. Returns the lines the command prints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchcal.config.compose import compose_options
from torchcal.core.errors import DataError, ModelError, TorchcalError
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.core.outputs import claim_file, claim_folder, csv_with_header, stamp_folder
from torchcal.data.plausibility import check_targets_not_metres
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import RobotModel, load_robot
from torchcal.kinematics.robot_checks import nominal_reach
from torchcal.motion.planner import PlannedMotion, PlanOptions, measure, plan_motion
from torchcal.motion.priority import TcpKinematics
from torchcal.motion.waypoints import Waypoints, load_waypoints

DEG = math.pi / 180.0


@dataclass(frozen=True)
class MotionOutcome:
    """What ``torchcal motion`` wrote and prints.

    Attributes:
        trajectory: the trajectory CSV.
        report: the report folder (``report.md``, ``report.html``, ``figures/``, ``motion.json``).
        metrics: scalar figures (mm, deg, s) as in ``motion.json``.
        lines: lines to print.
    """

    trajectory: Path
    report: Path
    metrics: dict
    lines: list[str]


def default_report_folder(out: Path) -> Path:
    """``TRAJ_report/`` next to ``TRAJ.csv``."""
    return out.with_name(f"{out.stem}_report")


#: The first waypoint's orientation read as radians this close to the start pose (deg) while read as
#: degrees (the contract) it is further than :data:`DEGREES_FAR_DEG` off: the angles are in radians.
RADIANS_NEAR_DEG, DEGREES_FAR_DEG = 5.0, 20.0


#: A waypoint further from the base than this many times the nominal reach is refused before planning
#: (the planner then finds no motion; nearer ones it reports where the path leaves the workspace).
BEYOND_REACH = 2.0


def refuse_implausible_path(robot: RobotModel, waypoints: Waypoints, start_deg: list[float]) -> None:
    """Refuse a path file in the wrong units (``x, y, z`` in metres, ``rx, ry, rz`` in radians) or with a
    waypoint beyond the arm's reach.

    Judged against the nominal robot: its reach over the joint range, and its TCP orientation at
    the start joints (the first waypoint is solved from there, so it is usually near it).

    Raises:
        DataError: naming the file, the column and the likely unit.
    """
    model = ErrorModel(robot)
    x = model.nominal_vector()
    reach = nominal_reach(robot)
    with torch.no_grad():
        start = model.tcp_pose(torch.tensor(start_deg, dtype=torch.float64).unsqueeze(0) * DEG, x)[0]
    check_targets_not_metres(waypoints.poses[:, :3, 3], reach, what="waypoint", path=str(waypoints.path),
                             row=waypoints.lines[0], advice="x, y, z look like metres; a path file gives mm")
    distance = waypoints.poses[:, :3, 3].norm(dim=-1)
    far = torch.nonzero(distance > BEYOND_REACH * reach).flatten()
    if len(far):  # no joint motion reaches it; found here, not after a path grid of that length is built
        k = int(far[0])
        raise DataError(f"the waypoint is {float(distance[k]) * 1e3:.6g} mm from the base, beyond the arm's nominal "
                        f"reach ({reach * 1e3:.6g} mm)", path=str(waypoints.path), row=waypoints.lines[k])
    first = waypoints.poses[0, :3, :3]
    written = tf.matrix_to_euler_xyz(first) * (180.0 / math.pi)  # the first row's rx, ry, rz as written
    if float(written.abs().max()) > 2 * math.pi:
        return  # beyond one turn: not radians
    as_degrees = math.degrees(float(tf.rotation_angle(first @ start[:3, :3].T)))
    as_radians = math.degrees(float(tf.rotation_angle(tf.euler_xyz_to_matrix(written) @ start[:3, :3].T)))
    if as_radians < RADIANS_NEAR_DEG and as_degrees > DEGREES_FAR_DEG:
        raise DataError(f"read in degrees the first waypoint's orientation is {as_degrees:.1f} deg from the start pose's, "
                        f"read in radians {as_radians:.1f} deg: rx, ry, rz look like radians; a path file gives deg",
                        path=str(waypoints.path), row=waypoints.lines[0], column="rx")


def failed_report_folder(report_dir: Path) -> Path:
    """Where a failed run's report goes when an earlier trajectory (and its report) must stay: ``<report>_failed``."""
    return report_dir.with_name(f"{report_dir.name}_failed")


def kinematics_of(robot: RobotModel, model_dir: Path | None) -> tuple[TcpKinematics, str]:
    """TCP kinematics of the nominal robot or of a calibrated model folder, and a line saying which."""
    if model_dir is None:
        error_model = ErrorModel(robot)
        x = error_model.nominal_vector()
        return TcpKinematics(error_model.table(x), error_model.T_base_0,
                             error_model.T_n_flange @ error_model.flange_from_tool(x)), f"nominal kinematics of {robot.name}"
    from torchcal.identify.joint_errors import JointSpaceErrors
    from torchcal.stages.store import load_model

    stored = load_model(model_dir)
    if stored.robot.dof != robot.dof or stored.robot.name != robot.name:
        raise ModelError(f"{model_dir}: the model is of robot '{stored.robot.name}' ({stored.robot.dof} joints), "
                         f"--robot is '{robot.name}' ({robot.dof} joints)")
    differs = [what for what, a, b in (("kinematic table", stored.robot.table, robot.table),
                                       ("joint limits", stored.robot.joint_limits, robot.joint_limits),
                                       ("base frame", stored.robot.T_base_0, robot.T_base_0),
                                       ("flange", stored.robot.T_n_flange, robot.T_n_flange))
               # 1e-6 (rad, m): a model folder keeps its robot file rewritten in deg and mm to 9 digits
               if a.shape != b.shape or not torch.allclose(a.to(torch.float64), b.to(torch.float64), rtol=0, atol=1e-6,
                                                           equal_nan=True)]
    if differs:  # the plan takes its limits from --robot and its kinematics from the model: both must be one robot
        raise ModelError(f"{model_dir}: the model's robot file and --robot differ in their {', '.join(differs)}; give the "
                         f"robot file the model was fitted with ({model_dir / 'robot.yaml'} or robot.urdf)")
    model, x = stored.model, stored.x.to(torch.float64).cpu()
    errors = JointSpaceErrors.from_metadata(stored.metadata)
    joint_map = None if errors.empty else (lambda q: errors.effective_joints(stored.robot, q))
    kin = TcpKinematics(model.table(x), model.T_base_0.cpu(), model.T_n_flange.cpu() @ model.flange_from_tool(x),
                        joint_map=joint_map)
    parts = ["geometry"] + (["joint-space errors"] if joint_map is not None else [])
    left = [stage.title() for stage in stored.stages() if stage.space == "tcp"]  # Cartesian stages: no joint-space chain
    note = f"; not used: {', '.join(left)} (no joint-space chain)" if left else ""
    return kin, f"calibrated kinematics of {model_dir} ({' and '.join(parts)}){note}"


def trajectory_csv(planned: PlannedMotion) -> str:
    """``t, q1..qN`` (s, deg), one row per sample."""
    n = planned.q.shape[1]
    lines = [",".join(["t"] + [f"q{j}" for j in range(1, n + 1)])]
    q_deg = planned.q / DEG
    for t, row in zip(planned.t, q_deg):
        lines.append(",".join([f"{t:.6f}"] + [f"{v:.12g}" for v in row]))
    return "\n".join(lines) + "\n"


def _is_trajectory(header: list[str]) -> bool:
    """The header :func:`trajectory_csv` writes: ``t, q1..qN``."""
    return len(header) > 1 and header[0] == "t" and header[1:] == [f"q{j}" for j in range(1, len(header))]


def _check_outputs(out: Path, report: Path) -> None:
    """The trajectory file and the report folder, refused before any work where torchcal may not write them."""
    claim_file(out, "trajectory", "--out", csv_with_header(_is_trajectory))
    claim_folder(report, "report", "--report")


def run_motion(robot_file: Path, path_file: Path, out: Path, overrides: list[str], *, model_dir: Path | None = None,
               report_dir: Path | None = None) -> MotionOutcome:
    """Plan the motion, write the report and (within tolerance and joint limits) the trajectory.

    Raises:
        TorchcalError: bad input (one line naming file, row and column or the option), or a motion
            that leaves the path tolerance or a joint range (the report is written first).
    """
    out = Path(out)
    report_dir = Path(report_dir) if report_dir is not None else default_report_folder(out)
    _check_outputs(out, report_dir)
    options = compose_options(PlanOptions(), overrides)
    robot = load_robot(robot_file)
    options.check(robot)
    waypoints = load_waypoints(path_file)
    refuse_implausible_path(robot, waypoints, options.start)
    kin, source = kinematics_of(robot, Path(model_dir) if model_dir is not None else None)
    planned = plan_motion(kin, robot, waypoints.poses, options)
    settings = options.priority()
    measured = measure(kin, planned, settings)
    metrics = {k: v for k, v in measured.items() if not isinstance(v, np.ndarray)}

    limits = robot.joint_limits.numpy()
    outside = (planned.q < limits[:, 0] - 1e-9) | (planned.q > limits[:, 1] + 1e-9)
    failures = []
    if metrics["path_error_max_mm"] > options.tolerance:
        k = int(np.argmax(measured["position_error_mm"]))
        seg = int(planned.segment[k])
        failures.append(f"path error {metrics['path_error_max_mm']:.3g} mm at t = {planned.t[k]:.3f} s (between rows "
                        f"{waypoints.lines[seg]} and {waypoints.lines[seg + 1]} of {waypoints.path}) exceeds the "
                        f"tolerance {options.tolerance:g} mm")
    between = metrics["path_error_between_samples_max_mm"]
    if between > options.between_tolerance:
        k = int(np.argmax(measured["between_samples_error_mm"]))
        # the error halfway falls with dt^2: the period that would meet the tolerance, with a margin
        shorter = 0.9 * options.dt * math.sqrt(options.between_tolerance / between)
        failures.append(f"halfway between the samples at t = {planned.t[k]:.3f} and {planned.t[k + 1]:.3f} s (joints "
                        f"interpolated linearly) the TCP passes {between:.3g} mm from the path, beyond "
                        f"between_tolerance={options.between_tolerance:g} mm: give dt={shorter:.2g} or less")
    over_v = np.array(metrics["joint_speed_max_deg_s"]) / np.array(metrics["joint_speed_limit_deg_s"])
    over_a = np.array(metrics["joint_accel_max_deg_s2"]) / np.array(metrics["joint_accel_limit_deg_s2"])
    for name, ratio in (("speed", over_v), ("acceleration", over_a)):
        if ratio.max() > 1.0 + 1e-6:
            j = int(np.argmax(ratio))
            failures.append(f"q{j + 1} {name} reaches {100 * ratio[j]:.1f} % of its limit")
    if outside.any():
        k, j = map(int, np.argwhere(outside)[0])
        failures.append(f"q{j + 1} = {planned.q[k, j] / DEG:.3f} deg at t = {planned.t[k]:.3f} s is outside its range "
                        f"[{limits[j, 0] / DEG:g}, {limits[j, 1] / DEG:g}] deg")
    metrics.update({"within_tolerance": not failures, "tolerance_mm": options.tolerance,
                    "between_tolerance_mm": options.between_tolerance,
                    "limit_source": planned.limit_source, "kinematics": source})

    inputs = (f"Path {waypoints.path} ({len(waypoints.lines)} waypoints, base frame), {source}; speed "
              f"{options.speed:g} mm/s, acceleration {options.accel:g} mm/s^2, interpolation period {options.dt:g} s; "
              f"joint limits: {planned.limit_source}.")
    method = ("Position first: the TCP position is the primary task, the orientation acts only in the position "
              "task's null space and yields near a singularity of the pose (damping of its own singular values below "
              f"orientation_eps = {options.orientation_eps:g}); limits are met by slowing down along the path "
              "(time-optimal time law), never by leaving it. The robot stops at every waypoint.")
    verdict = (f"Verdict: every sample within the path tolerance, the joint limits and ranges; trajectory written to {out}."
               if not failures else "Verdict: NOT written: " + "; ".join(failures) + ".")
    summary = [inputs, method, verdict]
    series = {
        "t": planned.t,
        "position_error_mm": measured["position_error_mm"],
        "orientation_deviation_deg": measured["orientation_deviation_deg"],
        "joint_speed_deg_s": measured["joint_speed_deg_s"],
        "joint_accel_deg_s2": measured["joint_accel_deg_s2"],
        "singular": (planned.sigma_orientation < settings.orientation_eps)
        | (planned.sigma_position < settings.position_eps),
        "sigma_orientation": planned.sigma_orientation,
        "sigma_position_mm": planned.sigma_position * 1e3,
        "tcp_speed_mm_s": np.linalg.norm(np.diff(kin.pose(torch.from_numpy(planned.q))[:, :3, 3].numpy(), axis=0),
                                         axis=-1) / options.dt * 1e3,
    }
    from torchcal.report.document import write_report
    from torchcal.report.motion import motion_report

    report = motion_report(f"Motion along {waypoints.path.name}", summary, metrics, series,
                           {"tolerance": options.tolerance, "between_tolerance": options.between_tolerance,
                            "orientation_eps": options.orientation_eps,
                            "position_eps": options.position_eps})
    if failures and out.exists():
        # an earlier run's trajectory stays, and so does the report that describes it
        report_dir = failed_report_folder(report_dir)
        claim_folder(report_dir, "report", "the failed run's report")
    write_report(report_dir, report)
    atomic_write_json(report_dir / "motion.json", metrics)
    stamp_folder(report_dir, "report")
    if failures:
        kept = f"; {out} not written" if not out.exists() else f"; {out} and its report kept from the earlier run"
        raise TorchcalError(f"{'; '.join(failures)}; report in {report_dir / 'report.md'}{kept}")
    atomic_write_text(out, trajectory_csv(planned))
    return MotionOutcome(trajectory=out, report=report_dir, metrics=metrics, lines=summary_lines(metrics, out, report_dir))


def _outside(value: float) -> str:
    return "no sample outside singular neighbourhoods" if math.isnan(value) else \
        f"{value:.3g} deg outside singular neighbourhoods"


def summary_lines(metrics: dict, out: Path, report_dir: Path) -> list[str]:
    """The lines ``torchcal motion`` prints."""
    peak_v, peak_a = np.array(metrics["joint_speed_max_deg_s"]), np.array(metrics["joint_accel_max_deg_s2"])
    speed = peak_v / np.array(metrics["joint_speed_limit_deg_s"])
    accel = peak_a / np.array(metrics["joint_accel_limit_deg_s2"])
    trajectory = f"trajectory: {out} ({metrics['n_samples']} samples, {metrics['duration_s']:.3f} s)"
    path_error = (f"path error: max {metrics['path_error_max_mm']:.2g} mm over the samples (start "
                  f"{metrics['start_error_mm']:.2g}, end {metrics['end_error_mm']:.2g}; tolerance "
                  f"{metrics['tolerance_mm']:g} mm), {metrics['path_error_between_samples_max_mm']:.2g} mm halfway "
                  f"between them (joints interpolated linearly; tolerance {metrics['between_tolerance_mm']:g} mm)")
    orientation = (f"orientation deviation: max {metrics['orientation_deviation_max_deg']:.3g} deg "
                   f"({_outside(metrics['orientation_deviation_regular_max_deg'])}; "
                   f"{metrics['samples_orientation_yielding']} samples where the orientation task is near-singular "
                   f"and yields, {metrics['samples_position_yielding']} where the position task does)")
    joints = (f"joint speed: max {peak_v.max():.1f} deg/s (q{int(np.argmax(peak_v)) + 1}), at most "
              f"{100 * speed.max():.0f} % of a limit (q{int(np.argmax(speed)) + 1}); joint acceleration: max "
              f"{peak_a.max():.0f} deg/s^2 (q{int(np.argmax(peak_a)) + 1}), at most {100 * accel.max():.0f} % of a "
              f"limit (q{int(np.argmax(accel)) + 1})")
    lines = [trajectory, path_error, orientation, joints]
    if metrics["first_waypoint_from_start_deg"] > 0.01:
        lines.append(f"first waypoint solved {metrics['first_waypoint_from_start_deg']:.3g} deg (largest joint) away from "
                     "start: the trajectory begins there, not at start")
    return [*lines, f"report: {report_dir / 'report.md'} (and report.html)"]
