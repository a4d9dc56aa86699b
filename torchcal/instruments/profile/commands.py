"""``torchcal fit`` and ``evaluate`` on a profile-scan file: the sensor's extrinsics.

``fit`` writes ``DIR/sensor.json`` (``R_flange_sensor``, ``t_flange_sensor_mm``, their sigmas,
the closed-form result, the placements and the fit statistics) and the robot file next to it,
so that ``evaluate --model DIR`` needs nothing else. Flange poses come from the nominal robot,
or from a calibrated model folder given as ``model=<dir>``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

from torchcal.config.compose import compose_options
from torchcal.config.schema import FitConfig, UnitOptions
from torchcal.core.errors import ModelError, TorchcalError
from torchcal.core.folder import verify_folder, write_member_json, write_member_text
from torchcal.core.metrics import distance_summary
from torchcal.core.overrides import renamed_keys, split_foreign_keys
from torchcal.instruments.base import FitOutcome
from torchcal.instruments.profile.closed_form import (
    ClosedFormResult,
    check_plane_coverage,
    closed_form,
    group_scans,
)
from torchcal.instruments.profile.data import ProfileData, load_profile
from torchcal.instruments.profile.model import (
    base_points,
    fit_planes,
    plane_distances,
    rotation_angle_deg,
)
from torchcal.instruments.profile.refine import RefineResult, refine
from torchcal.instruments.profile.search import search_start
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.robot import RobotModel, load_robot, robot_to_yaml
from torchcal.stages.store import copy_model, load_model

SENSOR_FILE = "sensor.json"


@dataclass
class ProfileFitConfig(UnitOptions):
    """Options of ``torchcal fit`` / ``evaluate`` on a profile file: the units of
    :mod:`torchcal.config.schema` (the same keys and checks as the tracker fit's) and its own.

    Attributes:
        joint_unit / length_unit: units of the file's ``q*`` and ``u, w`` (``deg``/``rad``, ``mm``/``m``).
        model_dir: calibrated model folder (``torchcal fit`` output) giving the flange poses;
            default: the nominal robot.
        start: ``auto`` (closed form; the rotation search only when no scans are pure
            translations of each other), ``closed_form`` or ``search``.
        orientation_tol_deg: flange orientations closer than this are one orientation.
        max_iterations: Levenberg-Marquardt iteration cap.
        device: ``cpu`` or a torch device string.
        check_limits: reject joints outside the robot's limits.
    """

    model_dir: str | None = None
    start: str = "auto"
    orientation_tol_deg: float = 0.1
    max_iterations: int = 100
    device: str = "cpu"
    check_limits: bool = True


def profile_config(overrides: list[str]) -> ProfileFitConfig:
    """Merge ``key=value`` overrides; robot-fit keys (``residual=``, ``method=``...) are ignored with a warning."""
    overrides = renamed_keys(overrides, {"model": "model_dir"}, what="a profile file")
    kept = split_foreign_keys(overrides, ProfileFitConfig, FitConfig, what="a profile file")
    config = compose_options(ProfileFitConfig(), kept)
    if config.start not in ("auto", "closed_form", "search"):
        raise TorchcalError(f"start must be auto, closed_form or search, got {config.start!r}")
    return config


def flange_poses(q: torch.Tensor, robot: RobotModel, model_dir: str | Path | None) -> tuple[torch.Tensor, str]:
    """``T_base_flange`` ``(S, 4, 4)`` of joints ``q`` (rad) and a description of its source."""
    if model_dir is None:
        return robot.flange_pose(q), "nominal"
    stored = load_model(model_dir)
    if stored.robot.dof != q.shape[1]:
        raise ModelError(f"{model_dir}: the calibrated robot has {stored.robot.dof} joints, the scans {q.shape[1]}")
    return stored.model.base_flange_pose(q.to(stored.x), stored.x), "calibrated"


def load_profile_file(data_path, robot: RobotModel, config: ProfileFitConfig) -> ProfileData:
    return load_profile(
        data_path,
        n_joints=robot.dof,
        joint_limits_rad=robot.joint_limits if config.check_limits else None,
        joint_unit=config.joint_unit,
        length_unit=config.length_unit,
        device=config.device,
    )


def estimate(data: ProfileData, T_base_flange: torch.Tensor, config: ProfileFitConfig) -> tuple[ClosedFormResult | None, RefineResult]:
    """Closed form (or search) start, then the joint refinement."""
    start = config.start
    if start == "auto":
        groups = group_scans(T_base_flange.to(data.uw), data.plane, config.orientation_tol_deg)
        start = "closed_form" if any(len(g.scans) >= 2 for g in groups) else "search"
        if start == "search":
            warnings.warn(
                f"{data.path}: no scans are pure translations of each other, so there is no closed form; "
                "starting from a rotation search",
                stacklevel=2,
            )
    seed = None
    if start == "closed_form":
        seed = closed_form(data, T_base_flange, orientation_tol_deg=config.orientation_tol_deg)
        R0, t0, normals0, offsets0 = seed.R, seed.t, seed.normals, seed.offsets
    else:
        R0, t0, normals0, offsets0 = search_start(data, T_base_flange)
        check_plane_coverage(data, base_points(T_base_flange.to(data.uw), data.point_scan, data.uw, R0, t0))
    return seed, refine(data, T_base_flange, R0, t0, normals0, offsets0, max_iterations=config.max_iterations)


def _distance_stats(d: torch.Tensor) -> dict:
    """Point-to-plane distances ``d`` (m, signed): ``rms_mm``, ``mean_abs_mm``, ``max_abs_mm``, ``p95_abs_mm``."""
    s = distance_summary(d.abs() * 1e3, "d", mean_key="mean_abs")
    return {"rms_mm": s["d_rms_mm"], "mean_abs_mm": s["d_mean_abs_mm"], "max_abs_mm": s["d_max_mm"], "p95_abs_mm": s["d_p95_mm"]}


def _write_robot(folder: Path, robot: RobotModel) -> str | None:
    """The robot file next to sensor.json (not inside a calibrated model folder, which has its own)."""
    if (folder / "calibration.json").is_file():
        return None
    if robot.source and Path(robot.source).suffix.lower() in (".urdf", ".xml"):
        path = write_member_text(folder, "robot.urdf", robot.urdf or Path(robot.source).read_text())
    else:
        path = write_member_text(folder, "robot.yaml", robot_to_yaml(robot))
    return path.name


def _rotation_vector_deg(R: torch.Tensor) -> list[float]:
    return [math.degrees(v) for v in tf.so3_log(R).tolist()]


def sensor_document(
    data: ProfileData, seed: ClosedFormResult | None, result: RefineResult, T_base_flange: torch.Tensor, config: ProfileFitConfig
) -> dict:
    """The content of ``sensor.json`` (mm, deg)."""
    cov = result.covariance[:6, :6].clone()
    scale = torch.tensor([180.0 / math.pi] * 3 + [1e3] * 3, dtype=cov.dtype, device=cov.device)
    cov6 = cov * scale.unsqueeze(0) * scale.unsqueeze(1)
    point_plane = data.point_plane()
    planes = []
    for k, label in enumerate(data.plane_labels):
        sel = point_plane == k
        sig = result.covariance.diagonal()[6 + 3 * k : 9 + 3 * k].clamp_min(0).sqrt()
        planes.append({
            "plane": label,
            "normal_base": result.normals[k].tolist(),
            "offset_mm": float(result.offsets[k]) * 1e3,
            "sigma_tilt_deg": [math.degrees(float(v)) for v in sig[:2]],
            "sigma_offset_mm": float(sig[2]) * 1e3,
            "n_scans": int((data.plane == k).sum()),
            "n_points": int(sel.sum()),
            "rms_mm": float(result.residuals[sel].pow(2).mean().sqrt()) * 1e3,
        })
    doc = {
        "format": "torchcal-profile-sensor/1",
        "frames": "R_flange_sensor, t_flange_sensor: p_flange = R p_sensor + t, p_sensor = (u, 0, w)",
        "units": {"lengths": "mm", "angles": "deg"},
        "R_flange_sensor": result.R.tolist(),
        "t_flange_sensor_mm": (result.t * 1e3).tolist(),
        "rotation_vector_deg": _rotation_vector_deg(result.R),
        "sigma_rotation_deg": result.sigma_rotation_deg,
        "sigma_t_mm": result.sigma_t_mm,
        "covariance": {
            "order": ["rot_x_deg", "rot_y_deg", "rot_z_deg", "t_x_mm", "t_y_mm", "t_z_mm"],
            "note": "rotations are small angles about the flange axes: R = exp(delta) R_flange_sensor",
            "matrix": cov6.tolist(),
        },
        "start": "closed_form" if seed is not None else "search",
        "closed_form": None,
        "planes": planes,
        "fit": {
            "n_points": data.n_points,
            "n_scans": data.n_scans,
            "n_planes": data.n_planes,
            "point_plane": _distance_stats(result.residuals),
            "sigma_residual_mm": result.sigma_residual * 1e3,
            "iterations": result.iterations,
            "converged": result.converged,
            "message": result.message,
            "cost_history": result.history,
        },
        "data": {"file": data.path, "sha256": data.sha256, "joint_unit": config.joint_unit, "length_unit": config.length_unit},
    }
    if seed is not None:
        seed_d = plane_distances(
            base_points(T_base_flange.to(data.uw), data.point_scan, data.uw, seed.R, seed.t), point_plane, seed.normals, seed.offsets
        )
        doc["closed_form"] = {
            "R_flange_sensor": seed.R.tolist(),
            "t_flange_sensor_mm": (seed.t * 1e3).tolist(),
            "orthonormalization": "SVD polar projection of [r1, r3 x r1, r3] onto SO(3)",
            "R_unit_columns": seed.R_unit.tolist(),
            "R_least_squares": seed.R_least_squares.tolist(),
            "orthogonality_error": seed.orthogonality_error,
            "rotation_groups": seed.rotation_groups,
            "normals_singular_values": seed.normals_singular_values,
            "translation_condition": seed.translation_condition,
            "point_plane_rms_mm": float(seed_d.pow(2).mean().sqrt()) * 1e3,
            "rotation_to_refined_deg": rotation_angle_deg(seed.R, result.R),
            "translation_to_refined_mm": float((seed.t - result.t).norm()) * 1e3,
        }
    return doc


def fit_profile(robot_path, data_path, out_dir, overrides: list[str], *, base_link=None, end_link=None, progress=None,
                previous: Path | None = None) -> FitOutcome:
    """``torchcal fit`` on a profile file: writes ``out_dir/sensor.json`` and the robot file.

    ``previous``: the folder this result replaces (``FitRequest.previous``); when it holds a
    calibrated model, the model's files are carried into ``out_dir`` and the sensor added to them.
    """
    config = profile_config(overrides)
    robot = load_robot(robot_path, base_link=base_link, end_link=end_link)
    data = load_profile_file(data_path, robot, config)
    T, source = flange_poses(data.q, robot, config.model_dir)
    seed, result = estimate(data, T, config)
    doc = sensor_document(data, seed, result, T, config)
    folder = Path(out_dir)
    folder.mkdir(parents=True, exist_ok=True)
    if previous is not None and Path(previous).resolve() != folder.resolve() and (Path(previous) / "calibration.json").is_file():
        verify_folder(previous)
        copy_model(previous, folder)
    robot_file = _write_robot(folder, robot)
    doc["flange_poses"] = {
        "source": source,
        "robot_file": robot_file,
        "model": str(Path(config.model_dir).resolve()) if config.model_dir else None,
    }
    write_member_json(folder, SENSOR_FILE, doc)
    return FitOutcome(folder)


def load_sensor(folder: str | Path) -> dict:
    """``sensor.json`` of a folder written by :func:`fit_profile`."""
    path = Path(folder) / SENSOR_FILE
    if not path.is_file():
        raise ModelError(f"{folder}: no {SENSOR_FILE} (fit a profile file into this folder first)")
    import json

    verify_folder(folder)
    try:
        doc = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelError(f"{path}: not a JSON document ({exc})") from None
    if not isinstance(doc, dict):
        raise ModelError(f"{path}: not a JSON object")
    return doc


def evaluate_profile(model_dir, data_path, overrides: list[str], *, register: bool = False) -> dict:
    """RMS point-to-plane distance of a stored ``sensor.json`` on a profile file.

    The placements of the target are nuisance parameters of each file, so each placement's
    plane is re-fitted (total least squares) to the points the stored extrinsics give;
    ``register`` changes nothing for this reason. Flange poses: ``model=<dir>`` if given, else the
    calibrated model of the folder (``calibration.json``), else the one ``fit`` used, else the
    folder's robot file.
    """
    config = profile_config(overrides)
    folder = Path(model_dir)
    doc = load_sensor(folder)
    model = config.model_dir
    if model is None and (folder / "calibration.json").is_file():
        model = str(folder)
    if model is None:
        recorded = (doc.get("flange_poses") or {}).get("model")
        if recorded and Path(recorded).is_dir():
            model = recorded
    if model is not None:
        robot = load_model(model).robot
    else:
        robot_file = (doc.get("flange_poses") or {}).get("robot_file")
        if not robot_file or not (folder / robot_file).is_file():
            raise ModelError(f"{folder}: no robot file next to {SENSOR_FILE}")
        robot = load_robot(folder / robot_file)
    data = load_profile_file(data_path, robot, config)
    T, source = flange_poses(data.q, robot, model)
    R = torch.tensor(doc["R_flange_sensor"], dtype=torch.float64, device=data.uw.device)
    t = torch.tensor(doc["t_flange_sensor_mm"], dtype=torch.float64, device=data.uw.device) * 1e-3
    points = base_points(T.to(data.uw), data.point_scan, data.uw, R, t)
    point_plane = data.point_plane()
    normals, offsets, _ = fit_planes(points, point_plane, data.n_planes)
    d = plane_distances(points, point_plane, normals, offsets)
    stats = _distance_stats(d)
    per_plane = {label: float(d[point_plane == k].pow(2).mean().sqrt()) * 1e3 for k, label in enumerate(data.plane_labels)}
    return {
        "n_points": data.n_points,
        "n_scans": data.n_scans,
        "n_planes": data.n_planes,
        "point_plane_rms_mm": stats["rms_mm"],
        "point_plane_mean_abs_mm": stats["mean_abs_mm"],
        "point_plane_max_mm": stats["max_abs_mm"],
        "point_plane_p95_mm": stats["p95_abs_mm"],
        "per_plane_rms_mm": per_plane,
        "planes": "re-fitted per placement",
        "flange_poses": source,
        "model": str(model_dir),
        "data": str(data_path),
        "registered": register,
    }
