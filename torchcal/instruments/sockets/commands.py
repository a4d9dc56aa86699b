"""``torchcal fit`` and ``evaluate`` on socket files (``placement, socket, q1..qN``).

``fit`` writes a normal model folder (same files as a tracker fit, ``T_reference = I``: the model
lives in the robot ``base`` frame), so ``export`` works on it unchanged; the fitted points, the
socket distance and the nominal/calibrated scores on the fitted rows are in ``calibration.json``
under ``sockets``. ``evaluate`` scores a model on socket rows: consistency (each group's point
fitted on the scored rows themselves) and distortion (error of the socket distance).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchcal.config.compose import compose_options
from torchcal.core.errors import TorchcalError
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.instruments.base import FitOutcome
from torchcal.instruments.sockets.data import load_socket_data
from torchcal.instruments.sockets.fit import fit_sockets_data
from torchcal.instruments.sockets.metrics import socket_metrics
from torchcal.instruments.sockets.plausibility import check_nominal, refuse_worse_than_nominal
from torchcal.kinematics.robot import load_robot
from torchcal.stages.geometry import model_joints
from torchcal.stages.store import load_model, save_model

GRAVITY_SETS = {"none": (), "wrist": ("tcp",), "elbow+wrist": ("elbow", "tcp")}


@dataclass
class SocketsFitConfig:
    """Options of ``fit`` / ``evaluate`` on a socket file.

    Attributes:
        joint_unit: ``deg`` (default, the contract's) or ``rad``.
        distance_mm: distance between sockets 0 and 1 of the fixture, mm (the scale).
        distance_weight: weight of the distance rows against the point rows (dimensionless; 100
            makes 1 um of distance error cost as much as 0.1 mm of point residual).
        placements: fit only the rows of these placements (default: all).
        gravity_compliance: joint sag under the arm's weight fitted with the geometry: ``none``
            (default), ``wrist`` or ``elbow+wrist`` (:mod:`torchcal.identify.compliance`).
        identifiability_tolerance: a column whose scaled independent part is below this stays at
            nominal (1e-3: parameters the configurations barely separate are not fitted).
        parallel_threshold_deg: Hayati switch of the error model.
        max_iterations: Levenberg-Marquardt cap.
        check_limits: refuse joints outside the robot file's limits (``false``: accept them).
        device: torch device of the fit.
    """

    joint_unit: str = "deg"
    distance_mm: float = 50.0
    distance_weight: float = 100.0
    placements: list[str] = field(default_factory=list)
    gravity_compliance: str = "none"
    identifiability_tolerance: float = 1e-3
    parallel_threshold_deg: float = 2.0
    max_iterations: int = 100
    check_limits: bool = True
    device: str = "cpu"

    @property
    def gravity_points(self) -> tuple[str, ...]:
        if self.gravity_compliance not in GRAVITY_SETS:
            raise TorchcalError(f"gravity_compliance must be one of {sorted(GRAVITY_SETS)}, got {self.gravity_compliance!r}")
        return GRAVITY_SETS[self.gravity_compliance]


def sockets_config(overrides: list[str]) -> SocketsFitConfig:
    config = compose_options(SocketsFitConfig(), list(overrides))
    config.gravity_points  # noqa: B018 - validates the option before anything is fitted
    if config.distance_mm <= 0:
        raise TorchcalError(f"distance_mm must be positive, got {config.distance_mm}")
    return config


def fit_sockets(robot_path, data_path, out_dir, overrides, *, base_link=None, end_link=None, progress=None) -> FitOutcome:
    """Fit a robot from socket constraints and write the model folder; returns it and the result lines.

    Refused before the fit: data the nominal robot cannot have recorded and too few configurations;
    after it, a calibrated robot worse than the nominal one (nothing is written then).
    """
    config = sockets_config(overrides)
    robot = load_robot(robot_path, base_link=base_link, end_link=end_link)
    data = load_socket_data(data_path, robot, joint_unit=config.joint_unit, check_limits=config.check_limits)
    if config.placements:
        data = data.select_placements(config.placements)
    with torch.no_grad():
        nominal_centres = robot.tcp_position(data.q)
        end_poses = robot.flange_pose(data.q)
    check_nominal(end_poses, data, config.distance_mm, robot.name)
    if progress is not None:
        progress(f"identifying {robot.name} from {len(data)} socket configurations")
    res = fit_sockets_data(robot, data, distance_mm=config.distance_mm, distance_weight=config.distance_weight,
                           parallel_threshold_deg=config.parallel_threshold_deg,
                           max_iterations=config.max_iterations, tolerance=config.identifiability_tolerance,
                           gravity_points=config.gravity_points, device=config.device)
    joints = JointSpaceErrors.of(res)
    nominal = socket_metrics(nominal_centres, data, config.distance_mm)
    with torch.no_grad():
        calibrated = socket_metrics(res.model.tcp_position(joints.effective_joints(robot, data.q.to(res.x)), res.x),
                                    data, config.distance_mm)
    refuse_worse_than_nominal(nominal, calibrated, data)
    ident = res.identifiability
    meta = {
        "method": "lm",
        "measurement": "sockets",
        "data": {"file": data.source, "sha256": data.sha256, "n_poses": len(data), "placements": list(data.placements)},
        "identifiability": {**ident.to_metadata(), "not_identifiable": res.not_identifiable},
        "residual_sigma_mm": res.sigma_residual_m * 1e3,
        "solver": {"iterations": res.solve.iterations, "message": res.solve.message, "cost_history": res.solve.history},
        "notes": res.notes,
        "sockets": {
            "frame": "robot base (T_reference = I; point constraints cannot see the base frame)",
            "distance_mm": config.distance_mm,
            "distance_weight": config.distance_weight,
            "points_mm": {f"{p}/{s}": (res.points[g] * 1e3).tolist() for g, (p, s) in enumerate(data.groups)},
            "point_sigmas_mm": {f"{p}/{s}": (res.point_sigma[g] * 1e3).tolist() for g, (p, s) in enumerate(data.groups)},
            "nominal": {k: v for k, v in nominal.items() if k != "per_placement"},
            "calibrated": {k: v for k, v in calibrated.items() if k != "per_placement"},
        },
        **joints.to_metadata(),
    }
    folder = save_model(Path(out_dir), robot, res.model, res.x, res.free, res.covariance, meta, training_q=data.q)
    return FitOutcome(folder, [
        ident.summary(),
        (f"sockets: consistency mean {nominal['consistency_mean_mm']:.3f} -> {calibrated['consistency_mean_mm']:.3f} mm, "
         f"distortion {nominal['distortion_mean_mm']:.3f} -> {calibrated['distortion_mean_mm']:.3f} mm on the "
         f"{len(data)} fitted configurations; {len(res.free)} robot parameters")])


def evaluate_sockets(model_dir, data_path, overrides, *, register: bool = False) -> dict:
    """Consistency and distortion (mm) of a model folder on a socket file (``register`` is implied).

    Data the stored nominal robot cannot have recorded are refused (:func:`check_nominal`).
    """
    config = sockets_config(overrides)
    stored = load_model(model_dir)
    data = load_socket_data(data_path, stored.robot, joint_unit=config.joint_unit, check_limits=config.check_limits)
    if config.placements:
        data = data.select_placements(config.placements)
    distance = float(stored.metadata.get("sockets", {}).get("distance_mm", config.distance_mm))
    q = data.q.to(stored.x)
    with torch.no_grad():
        predicted = stored.model.tcp_position(model_joints(stored, q), stored.x)
        nominal_centres = stored.robot.tcp_position(q)
        end_poses = stored.robot.flange_pose(q)
    # scores of a file the nominal robot cannot have recorded would be meaningless numbers
    check_nominal(end_poses, data, distance, stored.robot.name)
    nominal = socket_metrics(nominal_centres, data, distance)
    out = socket_metrics(predicted, data, distance)
    out.update({
        "n_poses": len(data),
        "nominal": {k: v for k, v in nominal.items() if k.startswith(("consistency", "distortion"))},
        "distance_mm": distance,
        "note": "each group's point is fitted on the scored rows themselves (a new placement is a new unknown point)",
        "model": str(model_dir),
        "data": str(data_path),
        "registered": True,
    })
    return out

