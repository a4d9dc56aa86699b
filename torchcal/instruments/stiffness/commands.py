"""``torchcal fit`` and ``evaluate`` for stiffness files (the stiffness instrument's handlers, see :mod:`torchcal.instruments.stiffness.plugin`).

``fit`` identifies the joint stiffness (:func:`torchcal.stiffness.identify.identify_stiffness`)
and writes a model folder: the robot's nominal geometry with the stiffness stage, or, with
``model=<model folder>``, a copy of that calibrated model with the stiffness added (its
kinematics are used for the Jacobians), so that geometry and stiffness form one model folder
that ``torchcal export`` turns into one compensator.

The parameterization (``parameters``) is ``classic`` (one spring about each joint axis),
``full`` (observable part of the 6-D diagonal per joint) or ``auto`` (default): K-fold
cross-validation over the file's poses (configuration groups by default,
:mod:`torchcal.data.folds`) fits both on each training part, scores the 3-D position
deflection error (mm) of the held-out poses, and keeps the simpler ``classic`` unless ``full`` is
better beyond noise (:func:`~torchcal.model_selection.compare.compare_candidates`); the chosen
one is then fitted on all poses. The comparison goes to ``stiffness.json`` (``model_selection``)
and, under ``"stiffness"``, to the folder's ``model_selection.json`` (next to a geometry fit's
comparison when the folder has one).

``evaluate`` predicts the deflection of every row of a stiffness file and reports
``deflection_rms_mm`` (RMS 3-D distance between measured and predicted deflection) and
``deflection_measured_rms_mm`` (RMS 3-D norm of the measured deflection), mm, instrument frame.
The instrument frame is the file's own: registered from its unloaded ``x, y, z`` when it has
them, the robot ``base`` otherwise (the data contract), so ``--register`` changes nothing here.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcal.config.compose import compose_options
from torchcal.config.schema import FitConfig, UnitOptions, ValidationOptions
from torchcal.core.errors import DataError, IdentifiabilityWarning, TorchcalError
from torchcal.core.folder import remove_member, write_member_json
from torchcal.core.hashing import sha256_file
from torchcal.core.metrics import distance_summary
from torchcal.core.overrides import renamed_keys, split_foreign_keys
from torchcal.data.folds import Folds, make_folds
from torchcal.instruments.base import FitOutcome
from torchcal.instruments.stiffness.data import StiffnessData, load_stiffness
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import RobotModel, load_robot
from torchcal.model_selection.compare import Candidate, Comparison, compare_candidates
from torchcal.stages.geometry import with_tool
from torchcal.stages.stiffness_store import save_stiffness
from torchcal.stages.store import copy_model, load_model, save_model
from torchcal.stiffness.identify import (
    DEFAULT_SIGMA_POSITION_M,
    DEFAULT_SIGMA_ROTATION_RAD,
    StiffnessEstimate,
    deflection_metrics,
    identify_stiffness,
    instrument_model,
)
from torchcal.stiffness.vjm import deflection

PARAMETERS = ("auto", "classic", "full")
"""Values of ``parameters``; the fitted candidates of ``auto`` are the others, simplest first."""
SELECTION_FILE = "model_selection.json"


@dataclass
class StiffnessFitConfig(ValidationOptions, UnitOptions):
    """``key=value`` options of ``fit`` / ``evaluate`` on a stiffness file: the units and the
    cross-validation of :mod:`torchcal.config.schema` (the same keys and checks as the tracker fit's)
    and its own.

    Attributes:
        joint_unit / length_unit: units of the file's ``q*`` (``deg`` | ``rad``) and of its
            ``d*``, ``x, y, z`` (``mm`` | ``m``).
        model_dir: calibrated model folder whose geometry the stiffness is added to (default: the
            nominal robot of ``--robot``).
        parameters: ``auto`` (default: the one of ``classic`` and ``full`` chosen by
            cross-validation, see the module docstring), ``classic`` (one spring about each
            joint axis) or ``full`` (observable part of the 6-D diagonal per joint).
        split: folds of that cross-validation (:func:`~torchcal.data.folds.make_folds`):
            ``grouped`` (default; near-twin configurations in one fold), ``blocks`` (contiguous
            blocks of the file's row order) or ``random`` (rows; for comparison only).
        cv_folds: number of folds.
        cv_groups: configuration regions (k-means clusters) of ``split=grouped``.
        seed: seed of the folds.
        use_rotation: fit the ``drx, dry, drz`` columns too (default: when the file has them).
        sigma_position_mm / sigma_rotation_deg: noise of one deflection component (weights and
            covariance).
        wrench_frame: frame of the file's wrench, ``tool`` (contract) or ``instrument``.
        tool_mm: nominal TCP in the flange frame (mm) replacing the robot file's.
        rank_tol: normalized singular value below which a direction is unobservable.
        poor_relative_std: relative std above which an entry is reported poorly determined.
        device: ``cpu`` or a torch device string.
        check_plausible: refuse a file whose loads or deflections are outside what an industrial
            arm shows (a unit mistake, see :func:`~torchcal.instruments.stiffness.data.check_plausible_units`);
            ``false`` for a rig outside those ranges.
    """

    model_dir: str | None = None
    parameters: str = "auto"
    use_rotation: bool | None = None
    sigma_position_mm: float = DEFAULT_SIGMA_POSITION_M * 1e3
    sigma_rotation_deg: float = math.degrees(DEFAULT_SIGMA_ROTATION_RAD)
    wrench_frame: str = "tool"
    tool_mm: list[float] | None = None
    rank_tol: float = 1e-7
    poor_relative_std: float = 0.25
    device: str = "cpu"
    check_plausible: bool = True


def stiffness_config(overrides: list[str]) -> StiffnessFitConfig:
    """Merge ``key=value`` overrides; tracker-fit keys that mean nothing here are ignored with a warning."""
    overrides = renamed_keys(overrides, {"model": "model_dir"}, what="a stiffness file")
    kept = split_foreign_keys(overrides, StiffnessFitConfig, FitConfig, what="a stiffness file")
    config = compose_options(StiffnessFitConfig(), kept)
    if config.wrench_frame not in ("tool", "instrument"):
        raise TorchcalError(f"wrench_frame must be 'tool' or 'instrument', got {config.wrench_frame!r}")
    if config.parameters not in PARAMETERS:
        raise TorchcalError(f"parameters must be one of {', '.join(PARAMETERS)}, got {config.parameters!r}")
    if config.cv_groups < 2:
        raise TorchcalError(f"cv_groups must be at least 2, got {config.cv_groups}")
    return config


def load_stiffness_file(path, n_joints: int, config: StiffnessFitConfig) -> StiffnessData:
    """:func:`load_stiffness` with the units and the plausibility check of ``config``."""
    return load_stiffness(
        path, n_joints=n_joints, joint_unit=config.joint_unit, length_unit=config.length_unit, device=config.device,
        check_plausible=config.check_plausible,
    )


def _identify(
    geometry: RobotModel | ErrorModel,
    data: StiffnessData,
    config: StiffnessFitConfig,
    parameters: str,
    x: torch.Tensor | None,
) -> StiffnessEstimate:
    """:func:`identify_stiffness` with the options of ``config`` and the given ``parameters``."""
    return identify_stiffness(
        geometry,
        data,
        x=x,
        parameters=parameters,
        use_rotation=config.use_rotation,
        sigma_position_m=config.sigma_position_mm * 1e-3,
        sigma_rotation_rad=math.radians(config.sigma_rotation_deg),
        wrench_frame=config.wrench_frame,  # type: ignore[arg-type]  # a str in the config schema, checked on load
        rank_tol=config.rank_tol,
        poor_relative_std=config.poor_relative_std,
        device=config.device,
    )


def parameter_folds(geometry: RobotModel | ErrorModel, data: StiffnessData, config: StiffnessFitConfig) -> Folds:
    """Folds of ``config.split`` over the poses of ``data`` (lever arms of the nominal robot)."""
    robot = geometry.robot if isinstance(geometry, ErrorModel) else geometry
    return make_folds(
        config.split, robot, data.q.cpu(), k=config.cv_folds, seed=config.seed, groups=config.cv_groups
    )


def cross_validate_parameters(
    geometry: RobotModel | ErrorModel,
    data: StiffnessData,
    folds: Folds,
    config: StiffnessFitConfig,
    *,
    x: torch.Tensor | None = None,
) -> Comparison:
    """Held-out deflection of ``classic`` and ``full`` over ``folds``, and the choice between them.

    On each fold both are identified on the training poses (as the final fit is, with
    ``geometry`` and ``x``) and predict the held-out poses with their own instrument frame
    (registered on the training poses: one set-up). Per-pose error: 3-D distance between
    measured and predicted position deflection, mm, instrument frame. Identifiability warnings
    of the fold fits are silenced: the final fit on all poses reports its own.
    """
    errors = {name: np.empty(len(data)) for name in PARAMETERS[1:]}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        for train, test in folds.splits():
            fitted = data.subset(torch.as_tensor(train, device=data.q.device))
            held_out = data.subset(torch.as_tensor(test, device=data.q.device))
            for name, per_pose in errors.items():
                estimate = _identify(geometry, fitted, config, name, x)
                device = estimate.x.device
                predicted = estimate.predict(held_out.q.to(device), held_out.wrench.to(device))[:, :3]
                per_pose[test] = ((predicted - held_out.deflection.to(predicted)).norm(dim=-1) * 1e3).cpu().numpy()
    candidates = [
        Candidate("classic", errors["classic"], detail="one spring about each joint axis"),
        Candidate("full", errors["full"], detail="observable part of the 6-D diagonal per joint"),
    ]
    return compare_candidates(candidates, folds.units(), f"held-out TCP deflection, {folds.description}")


def _write_selection(folder: Path, selection: dict | None) -> None:
    """Put ``selection`` under ``"stiffness"`` in the folder's ``model_selection.json`` (``None``: remove it).

    The rest of the file (a geometry fit's comparison, copied with ``model=``) is kept.
    """
    path = folder / SELECTION_FILE
    content = json.loads(path.read_text()) if path.is_file() else {}
    content.pop("stiffness", None)
    if selection is not None:
        content["stiffness"] = selection
    if content:
        write_member_json(folder, SELECTION_FILE, content)
    else:
        remove_member(folder, SELECTION_FILE)


def fit_stiffness(
    robot_path: str | Path,
    data_path: str | Path,
    out_dir: str | Path,
    overrides: list[str],
    *,
    base_link: str | None = None,
    end_link: str | None = None,
    progress=None,
) -> FitOutcome:
    """``torchcal fit`` on a stiffness file: choose the parameterization, identify, write ``out_dir``.

    Returns the folder and the result lines (the parameter comparison, the stiffnesses)."""
    config = stiffness_config(overrides)
    out = Path(out_dir)
    robot = with_tool(load_robot(robot_path, base_link=base_link, end_link=end_link), config)  # type: ignore[arg-type]  # reads only tool_mm
    stored = None
    if config.model_dir is not None:
        stored = load_model(config.model_dir, device=config.device)
        if stored.robot.dof != robot.dof:
            raise TorchcalError(f"model {config.model_dir} has {stored.robot.dof} joints but {robot_path} has {robot.dof}")
        if config.tool_mm is not None:
            warnings.warn("tool_mm is ignored with model=: the calibrated tool of the model is used", stacklevel=2)
    data = load_stiffness_file(data_path, robot.dof, config)
    geometry = stored.model if stored is not None else robot
    x = stored.x if stored is not None else None
    parameters, selection, comparison = config.parameters, None, None
    if parameters == "auto":
        try:
            folds = parameter_folds(geometry, data, config)
        except DataError as err:
            parameters = "classic"
            selection = {"chosen": parameters, "reason": f"no cross-validation ({err}): the simpler model"}
            warnings.warn(f"parameters=auto: {err}; fitting parameters=classic", stacklevel=2)
        else:
            comparison = cross_validate_parameters(geometry, data, folds, config, x=x)
            parameters, selection = comparison.chosen, comparison.to_dict()
    estimate = _identify(geometry, data, config, parameters, x)
    wrench = data.wrench
    meta: dict[str, Any] = {
        "data": {
            "file": str(data_path),
            "sha256": sha256_file(data_path),
            "n_poses": len(data),
            "joint_unit": config.joint_unit,
            "length_unit": config.length_unit,
        },
        "training_wrench": {
            "max_force_n": float(wrench[:, :3].norm(dim=-1).max()),
            "max_torque_nm": float(wrench[:, 3:].norm(dim=-1).max()),
        },
        "geometry": {"source": "calibrated model", "model": str(config.model_dir)} if stored else {"source": "nominal robot", "robot": str(robot_path)},
        "fit_metrics": deflection_metrics(estimate, data),
    }
    if selection is not None:
        meta["model_selection"] = selection
    if config.model_dir is not None:  # stored was loaded from it
        if out.resolve() != Path(config.model_dir).resolve():
            copy_model(config.model_dir, out)
    else:
        # no geometric calibration: the nominal table, the loading set-up's instrument frame
        model = ErrorModel(robot, T_instrument_base=estimate.model.T_reference, device=config.device)
        empty = torch.zeros(0, dtype=torch.long)
        save_model(
            out, robot, model, estimate.x, empty, torch.zeros(0, 0, dtype=torch.float64),
            {
                "method": "none (nominal geometry; stiffness only)",
                "data": {"file": str(data_path), "sha256": meta["data"]["sha256"], "n_poses": len(data)},
                "notes": ["geometry not calibrated: fit a tracker file and pass model=<folder> to combine"],
            },
        )
    save_stiffness(out, estimate, meta)
    if comparison is not None:
        table = comparison.format_table()
        assert selection is not None  # set with the comparison
        selection = {**selection, "table": table}
    _write_selection(out, selection)
    lines = [table] if comparison is not None else []
    return FitOutcome(out, lines + _summary(estimate, meta["fit_metrics"]))


def _summary(estimate, metrics: dict) -> list[str]:
    parts = [f"{n} = {k:.4g} (+-{100 * s:.1f} %)" for n, k, s in zip(estimate.names, estimate.stiffness.tolist(), estimate.relative_std.tolist())]
    lines = ["stiffness: " + "; ".join(parts)]
    if estimate.identifiability.unobservable:
        lines.append(f"not observable (rigid): {', '.join(estimate.identifiability.unobservable)}")
    lines.append(
        f"training deflection RMS {metrics['deflection_rms_mm']:.4f} mm of {metrics['deflection_measured_rms_mm']:.4f} mm measured"
    )
    return lines


def predicted_deflection(stored, data: StiffnessData) -> torch.Tensor:
    """Deflection ``(B, 6)`` ``[dp (m); dphi (rad)]`` the model folder predicts for ``data``.

    Geometry from the model, compliance from its stiffness stage, instrument frame from the file
    (see the module docstring).
    """
    stage = stored.stiffness
    if stage is None:
        raise TorchcalError(f"{stored.folder}: the model has no stiffness stage (fit it with a stiffness file)")
    model, x = instrument_model(stored.model, data, stored.x, device=stored.x.device)
    q, wrench = data.q.to(x.device), data.wrench.to(x.device)
    return deflection(model, q, x, stage.compliance.to(x), wrench, wrench_frame=stage.wrench_frame)


def evaluate_stiffness(model_dir: str | Path, data_path: str | Path, overrides: list[str], *, register: bool = False) -> dict:
    """``torchcal evaluate`` on a stiffness file: deflection metrics, mm (and deg when it has rotations)."""
    config = stiffness_config(overrides)
    stored = load_model(model_dir, device=config.device)
    data = load_stiffness_file(data_path, stored.robot.dof, config)
    predicted = predicted_deflection(stored, data)
    measured = data.deflection.to(predicted)
    err = (predicted[:, :3] - measured).norm(dim=-1) * 1e3
    size = measured.norm(dim=-1) * 1e3
    metrics: dict[str, Any] = {
        "n_poses": len(data),
        **distance_summary(err, "deflection"),
        "deflection_measured_rms_mm": float(size.pow(2).mean().sqrt()),
        "deflection_ratio": float(err.pow(2).mean().sqrt() / size.pow(2).mean().sqrt().clamp_min(1e-300)),
    }
    if data.rotation is not None:
        rot_err = (predicted[:, 3:] - data.rotation.to(predicted)).norm(dim=-1)
        metrics["rotation_rms_deg"] = math.degrees(float(rot_err.pow(2).mean().sqrt()))
        metrics["rotation_measured_rms_deg"] = math.degrees(float(data.rotation.norm(dim=-1).pow(2).mean().sqrt()))
    metrics.update(
        {
            "model": str(model_dir),
            "data": str(data_path),
            "instrument_frame": "registered from the file's x, y, z" if data.unloaded is not None else "robot base",
            "registered": register,
        }
    )
    return metrics

