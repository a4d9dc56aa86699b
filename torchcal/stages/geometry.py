"""The geometry stage: fit a robot's geometry (and joint-space terms) to measured points, store it, predict.

The model-selected fit of ``torchcal fit`` on tracker points (structure chosen by grouped
cross-validation), the same fit without selection, the stored model's predictions
(``instrument`` frame, m) and the errors a stored model leaves on a measurement file. Every
instrument whose fit ends in a robot geometry writes its model folder through :func:`save_fit`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from torchcal.config.schema import FitConfig
from torchcal.core.errors import DataError
from torchcal.core.workers import in_background, resolve_jobs
from torchcal.data.folds import make_folds
from torchcal.data.measurements import Measurements
from torchcal.identify import IDENTIFIERS
from torchcal.identify.calibrate import CalibrationResult, calibrate, register_instrument
from torchcal.identify.compliance import POINT_SETS
from torchcal.identify.harmonics import HARMONIC_SETS, is_series
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.identify.joint_fit import fit_joint_errors, joint_error_options, predicted_positions
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.problem import CalibrationProblem
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import RobotModel
from torchcal.kinematics.transforms import rigid_registration
from torchcal.model_selection.compare import compare_candidates
from torchcal.model_selection.prior_scale import (
    cross_validate_prior_scales,
    evidence_prior_scales,
    fold_key,
    selection_record,
    selection_summary,
)
from torchcal.model_selection.structure import cross_validate_structures, structure_label
from torchcal.residual import head_names
from torchcal.stages.base import GeometryStage
from torchcal.stages.prediction_uncertainty import (
    calibrate_errors,
    point_jacobian,
    write_uncertainty,
)
from torchcal.stages.prior_options import base_spec, parse_scale, prior_metadata, prior_warning
from torchcal.stages.store import StoredModel, save_model


def registered_errors(predicted_base: torch.Tensor, measured: torch.Tensor) -> torch.Tensor:
    """Errors after the best rigid registration of ``predicted_base`` onto ``measured``."""
    transform = rigid_registration(predicted_base, measured)
    aligned = predicted_base @ transform[:3, :3].T + transform[:3, 3]
    return measured - aligned


#: How the "before" of every report and console line is obtained (the protocol stated next to it).
NOMINAL_PROTOCOL = "nominal robot, instrument frame and tool fitted to these poses"


def nominal_fit(robot: RobotModel, data: Measurements) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The nominal robot as a user would fit it: instrument frame (6) and tool point (3), MDH table at nominal.

    Returns ``(errors, T_instrument_base, tool)``: ``measured - predicted`` ``(n, 3)`` in the
    instrument frame (m), the fitted ``(4, 4)`` transform and the tool point in ``flange`` (m).
    The frame starts from the closed-form registration; frame and tool are then refined together
    by Levenberg-Marquardt.
    """
    data = data.to("cpu")
    model = ErrorModel(robot, T_instrument_base=register_instrument(robot, data))
    layout = model.layout
    free = torch.arange(layout.base_slice.start, layout.tool_slice.start + 3)
    x = LevenbergMarquardt(max_iterations=60).solve(CalibrationProblem(model, data, free), model.nominal_vector()).x
    errors = data.position - model.tcp_position(data.q, x)
    return errors, model.instrument_from_base(x), x[layout.tool_slice][:3].clone()


def nominal_errors(robot: RobotModel, data: Measurements) -> torch.Tensor:
    """Errors of the nominal robot with instrument frame and tool fitted to ``data`` (the fair 'before').

    A user's "nominal" has both fitted: the instrument frame alone (:func:`registered_errors` of
    the nominal positions) leaves the error of a tool guessed a few mm off and overstates what
    the calibration gains.
    """
    return nominal_fit(robot, data)[0]


def with_tool(robot: RobotModel, config: FitConfig) -> RobotModel:
    """``robot`` with the configured nominal tool, if one is configured."""
    if config.tool_mm is None:
        return robot
    if len(config.tool_mm) != 3:
        raise DataError(f"tool_mm needs 3 values (x, y, z in mm), got {list(config.tool_mm)}")
    return replace(robot, tool=torch.tensor(config.tool_mm, dtype=torch.float64) * 1e-3)


def describe_structure(result: CalibrationResult) -> str:
    """``geometry``, ``geometry + gravity compliance + joint harmonics``, ... of a fit result."""
    terms = [t for t, present in (("gravity compliance", result.compliance is not None),
                                  ("joint harmonics", result.harmonics is not None)) if present]
    return "geometry" + "".join(f" + {t}" for t in terms)


def make_config_folds(robot: RobotModel, data: Measurements, config: FitConfig):
    """The folds every data-driven choice of this fit is judged on (``config.split``)."""
    order = np.asarray(data.line_numbers) if data.line_numbers else None
    return make_folds(config.split, robot, data.q, k=config.cv_folds, seed=config.seed, order=order,
                      groups=config.cv_groups, series=data.series)


def geometry_fitter(robot: RobotModel, config: FitConfig, prior=None, cache: dict | None = None,
                    start: CalibrationResult | None = None):
    """``geometry(train, units=None, start=None)``: the geometric fit of ``config`` (``units``: see :func:`calibrate`).

    ``prior``: a :class:`~torchcal.identify.prior.PriorSpec` (MAP fit) or ``None`` (rank cut).
    ``cache``: fits of training parts already made with this prior (``prior_scale.fold_key``).
    ``start``: a MAP fit every fit starts its iterations from (the fit on all poses with this
    prior: a fold's fit then needs a few steps instead of a solve from nominal; the minimum, hence
    the held-out score, is the fold's own); a ``start`` given to ``geometry`` overrides it.
    """
    default_start = start

    def geometry(train: Measurements, units: np.ndarray | None = None,
                 start: CalibrationResult | None = None) -> CalibrationResult:
        if cache and units is None:
            hit = cache.get(fold_key(train))
            if hit is not None:
                return hit
        return calibrate(robot, train, identifier=IDENTIFIERS[config.method](**_identifier_options(robot, config)),
                         parallel_threshold_deg=config.parallel_threshold_deg, device=config.device, units=units,
                         prior=prior, start=start if start is not None else default_start)

    return geometry


def choose_prior(robot: RobotModel, data: Measurements, config: FitConfig, progress=None):
    """The prior of ``config`` (``None`` without one), its scale chosen by the data when ``auto`` or ``cv``.

    Returns ``(spec, selection record or None, per-fold fits of the chosen spec, fit on all poses or None)``:
    ``auto`` chooses by the evidence (one fit per candidate on all poses; the chosen one's fit is
    returned as the warm start of every later fit), ``cv`` by the grouped cross-validation (its
    per-fold fits of the chosen spec are returned for the structure CV to reuse).
    """
    base = base_spec(robot, config)
    scale = parse_scale(config.prior_scale)
    if base is None:
        return None, None, {}, None
    if isinstance(scale, float):
        return replace(base, scale=scale), None, {}, None
    if scale == "evidence":
        chosen, record, full = evidence_prior_scales(lambda spec: geometry_fitter(robot, config, spec), base, data,
                                                     progress=progress)
        return chosen, record, {}, full
    folds = make_config_folds(robot, data, config)
    chosen, comparison, fits = cross_validate_prior_scales(
        data, lambda spec: geometry_fitter(robot, config, spec), base, folds, progress=progress)
    return chosen, selection_record(comparison, chosen), fits, None


def _identifier_options(robot: RobotModel, config: FitConfig) -> dict:
    """LASSO's penalty is chosen by the same kind of folds as every other choice."""
    if config.method != "lasso":
        return {}
    return {"folds": config.cv_folds, "seed": config.seed, "split": config.split, "robot": robot}


def structure_options(config: FitConfig) -> list[tuple[str, str]]:
    """The joint-space structures ``config`` lets the cross-validation choose from, simplest first."""
    try:
        return joint_error_options(config.gravity_compliance, config.joint_harmonics)
    except ValueError as exc:
        raise DataError(str(exc)) from None


def fit_with_selection(robot: RobotModel, data: Measurements, config: FitConfig, *, progress=None):
    """Identify the geometry and the joint-space terms the cross-validation supports.

    Returns ``(result, structure_cv)``. The cross-validation (folds of ``config.split``) runs
    when there is something to choose: several joint-space options (``auto``) or residual heads
    to judge later (``structure_cv`` carries the per-fold fits they learn on); otherwise
    ``structure_cv`` is ``None``. ``progress(text)`` is called before long steps.
    """
    if config.method not in IDENTIFIERS:
        raise DataError(f"unknown method '{config.method}'; choose one of {sorted(IDENTIFIERS)}")
    if config.residual != "none":
        head_names(config.residual)  # an unknown head is refused before anything is fitted
    options = structure_options(config)
    few = pose_count_warning(len(data), int(ErrorModel(robot, parallel_threshold_deg=config.parallel_threshold_deg)
                                             .default_active().sum()))
    if few is not None:
        warnings.warn(few, stacklevel=2)
    prior, prior_selection, prior_fits, full = choose_prior(robot, data, config, progress=progress)
    geometry = geometry_fitter(robot, config, prior, prior_fits, start=full)
    structure = None
    gravity, harmonics = options[0]
    # the CV also calibrates the prediction uncertainty (stages.prediction_uncertainty)
    if len(options) > 1 or config.residual != "none" or config.uncertainty != "none":
        # a ready worker makes the folds: it imported their k-means at its start (config.workers), and
        # this process imports meanwhile what it will need later (core.workers.import_while_waiting)
        with in_background(make_config_folds, robot, data, config, jobs=resolve_jobs(config.jobs)) as pending:
            pass
        folds = pending.result()
        structure = cross_validate_structures(robot, data, geometry, options, folds, progress=progress,
                                              harmonic_min_range_deg=config.harmonic_min_range_deg,
                                              jobs=resolve_jobs(config.jobs))
        structure.prior, structure.prior_start = prior, full
        gravity, harmonics = structure.chosen
        if is_series(HARMONIC_SETS[harmonics]) and config.head_time_check and config.split != "blocks":
            gravity, harmonics = _learned_time_check(robot, data, config, geometry, structure, progress)
    if progress is not None:
        progress("fitting the chosen structure on all poses")
    # the regions the CV holds out also say which residuals may be correlated (identify.uncertainty)
    units = structure.folds.groups if structure is not None else None
    result = fit_joint_errors(robot, data, geometry(data, units, start=full), POINT_SETS[gravity], HARMONIC_SETS[harmonics],
                              config.harmonic_min_range_deg, units=units)
    if few is not None:
        result.notes.append(f"warning: {few}")
    refuse_implausible_residual(robot, data, result)
    if prior_selection is not None:
        result.prior_selection = prior_selection
        result.notes.append(selection_summary(prior_selection))
    if structure is not None and len(options) > 1:
        comparison = structure.comparison
        result.notes.append(f"structure chosen by {comparison.protocol}: "
                            + ", ".join(f"{r['name']} {r['cv_rms_mm']:.4f} mm" for r in comparison.rows)
                            + f" -> {structure_label(gravity, harmonics)} ({comparison.reason})")
    return result, structure


def _learned_time_check(robot: RobotModel, data: Measurements, config: FitConfig, geometry, structure,
                        progress) -> tuple[str, str]:
    """A learned joint-space model (a Fourier series) that the CV chose must also beat the best classic
    structure on contiguous blocks of measurement order, as a residual head must: one that learned a
    drift of the series wins over regions and loses over time. Returns the option to fit."""
    chosen = structure.chosen
    classic = [o for o in structure.options if not is_series(HARMONIC_SETS[o[1]])]
    if not classic:
        return chosen
    by_name = {c.name: c for c in structure.candidates}
    rival_cmp = compare_candidates([by_name[structure_label(*o)] for o in classic], structure.folds.units(),
                                   structure.folds.description)
    rival = next(o for o in classic if structure_label(*o) == rival_cmp.chosen)
    if progress is not None:
        progress("checking the learned joint-space model on blocks of measurement order")
    order = np.asarray(data.line_numbers) if data.line_numbers else None
    blocks = make_folds("blocks", robot, data.q, k=config.cv_folds, seed=config.seed, order=order,
                        series=data.series)
    check = cross_validate_structures(robot, data, geometry, [rival, chosen], blocks,
                                      harmonic_min_range_deg=config.harmonic_min_range_deg, jobs=resolve_jobs(config.jobs))
    rows = ", ".join(f"{r['name']} {r['cv_rms_mm']:.4f} mm" for r in check.comparison.rows)
    comparison = structure.comparison
    if check.chosen == chosen:
        comparison.reason += f"; it wins on blocks of measurement order too ({rows})"
        return chosen
    comparison.reason += (f"; refused on blocks of measurement order ({rows}: {check.comparison.reason}), "
                          f"so {structure_label(*rival)}")
    comparison.chosen = structure_label(*rival)
    return rival


def fit(robot: RobotModel, data: Measurements, config: FitConfig, *, progress=None) -> CalibrationResult:
    """Geometric identification plus the joint-space errors chosen by cross-validation (:func:`fit_with_selection`)."""
    return fit_with_selection(robot, data, config, progress=progress)[0]


def cross_validate_stored_structure(stored: StoredModel, data: Measurements, config: FitConfig):
    """The structure of a model folder alone, cross-validated on ``config``'s folds (for its heads)."""
    terms = JointSpaceErrors.from_metadata(stored.metadata)
    points = tuple(terms.compliance.points) if terms.compliance is not None else ()
    gravity = next(name for name, members in POINT_SETS.items() if members == points)
    harmonics = terms.harmonics.set_name if terms.harmonics is not None else "none"
    folds = make_config_folds(stored.robot, data, config)
    prior = None
    if stored.metadata.get("prior"):  # the folder's fit had a prior: its scale as chosen then
        base = base_spec(stored.robot, config)
        prior = None if base is None else replace(base, scale=float(stored.metadata["prior"]["scale"]))
    structure = cross_validate_structures(stored.robot, data, geometry_fitter(stored.robot, config, prior),
                                          [(gravity, harmonics)], folds, harmonic_min_range_deg=config.harmonic_min_range_deg,
                                          jobs=resolve_jobs(config.jobs))
    structure.prior = prior
    return structure


#: Corrections of the MDH table beyond these are far outside manufacturing tolerances (mm, deg).
TOLERANCE_MM, TOLERANCE_DEG = 20.0, 2.0
#: Fewer measured coordinates per identified parameter than this gives a warning.
MIN_EQUATIONS_PER_PARAMETER = 3.0


def pose_count_warning(n_poses: int, n_parameters: int, coordinates_per_pose: int = 3) -> str | None:
    """A warning when ``n_poses`` give fewer than :data:`MIN_EQUATIONS_PER_PARAMETER` coordinates per parameter."""
    ratio = n_poses * coordinates_per_pose / max(n_parameters, 1)
    if ratio >= MIN_EQUATIONS_PER_PARAMETER:
        return None
    need = math.ceil(MIN_EQUATIONS_PER_PARAMETER * n_parameters / coordinates_per_pose)
    return (f"{n_poses} poses give {n_poses * coordinates_per_pose} coordinates for {n_parameters} parameters "
            f"({ratio:.2f} per parameter): the fit follows the noise; measure at least {need} poses")


#: A calibrated model that still misses its own poses by this much (RMS, mm) does not describe the
#: measured robot: real arms calibrate to 0.02-0.5 mm, deflections add a few mm at most.
IMPLAUSIBLE_RESIDUAL_MM = 10.0


def refuse_implausible_residual(robot: RobotModel, data: Measurements, result: CalibrationResult) -> None:
    """Refuse a fit that leaves more than :data:`IMPLAUSIBLE_RESIDUAL_MM` RMS on its own poses.

    No robot built within manufacturing tolerances leaves that once calibrated: the robot file (or
    the measurement set-up) is wrong. With a prior the MDH table cannot run off to absorb such a
    file (the corrections' own warning then stays silent), so the misfit itself is named.

    Raises:
        DataError: naming the residual and the likely causes (a fit runs staged: nothing is written).
    """
    errors = data.position.to(result.x.device) - predicted_positions(result, data.q.to(result.x.device))
    rms_mm = float(errors.norm(dim=-1).pow(2).mean().sqrt()) * 1e3
    if rms_mm > IMPLAUSIBLE_RESIDUAL_MM:
        raise DataError(f"after calibration the model of {robot.name} still misses the measured points by "
                        f"{rms_mm:.1f} mm RMS (a calibrated arm: well under 1 mm): the robot file is likely not "
                        "this robot's (another model, joint signs or zeros, a mirrored frame), or the joint "
                        "columns and the points are not the same poses; nothing was written", path=data.source)


def implausible_corrections(result: CalibrationResult) -> str | None:
    """A warning naming MDH corrections far beyond manufacturing tolerances (usually a wrong robot file)."""
    model = result.model
    layout = model.layout
    delta = (result.x.detach().cpu() - model.nominal_vector().cpu()) * layout.unit_scale()
    angle = layout.is_angle()
    found = []
    for i in range(layout.table_slice.start, layout.table_slice.stop):
        limit, unit = (TOLERANCE_DEG, "deg") if bool(angle[i]) else (TOLERANCE_MM, "mm")
        if abs(float(delta[i])) > limit:
            found.append(f"{layout.names[i]} {float(delta[i]):+.4g} {unit}")
    if not found:
        return None
    return (f"corrections far beyond manufacturing tolerances ({TOLERANCE_MM:g} mm, {TOLERANCE_DEG:g} deg): "
            f"{', '.join(found)}; check the robot file ({model.robot.name}) against the robot")


def save_fit(folder: Path, robot: RobotModel, data: Measurements, result: CalibrationResult, extra: dict,
             structure=None, uncertainty: str = "conformal") -> Path:
    """Write the model folder of a geometry fit; implausible corrections are warned about and noted in it.

    ``structure``: the fit's cross-validation (:func:`fit_with_selection`); with it and
    ``uncertainty`` other than ``none``, the per-pose prediction uncertainty is calibrated on the
    chosen structure's out-of-fold errors and written too (``uncertainty.json``).
    """
    for warning in (implausible_corrections(result), prior_warning(result)):
        if warning is not None:
            warnings.warn(warning, stacklevel=2)
            result.notes.append(f"warning: {warning}")
    ident = result.identifiability
    meta = {
        "method": result.method,
        "data": {"file": data.source, "sha256": data.sha256, "n_poses": len(data)},
        "identifiability": ident.to_metadata(),
        "residual_sigma_mm": result.sigma_residual_m * 1e3,
        "solver": {"iterations": result.solve.iterations, "message": result.solve.message, "cost_history": result.solve.history},
        "notes": result.notes,
        "prior": prior_metadata(result),
        **extra,
    }
    meta.update(JointSpaceErrors.of(result).to_metadata())
    folder = Path(folder)
    # a new fit invalidates what an earlier fit into this folder learned on top of its geometry
    from torchcal.core.folder import remove_member

    for stale in ("residual.safetensors", "residual.json", "model_selection.json", "uncertainty.json"):
        remove_member(folder, stale)
    joint = (None if result.joint_covariance is None or result.joint_coefficients is None
             else (result.joint_covariance, result.joint_coefficients))
    folder = save_model(folder, robot, result.model, result.x, result.free, result.covariance, meta, training_q=data.q,
                        joint_covariance=joint)
    if structure is not None and uncertainty != "none":
        label = structure.comparison.chosen
        joints = JointSpaceErrors.of(result).effective_joints(robot, data.q)
        jac = point_jacobian(result.model, result.x, result.free, joints)
        write_uncertainty(folder, calibrate_errors(jac, result.covariance, structure.comparison.errors_mm[label],
                                                   structure.comparison.protocol, uncertainty))
    return folder


def model_joints(stored: StoredModel, q: torch.Tensor) -> torch.Tensor:
    """Joints (rad) to put through the geometric chain: ``q`` plus every stored joint-space error."""
    return JointSpaceErrors.from_metadata(stored.metadata).effective_joints(stored.robot, q)


def predict_positions(
    stored: StoredModel, q: torch.Tensor, temperature: torch.Tensor | None = None, wrench: torch.Tensor | None = None
) -> torch.Tensor:
    """Model prediction of TCP positions (instrument frame, m), compliance and residual head included.

    With a ``wrench`` ``(n, 6)`` (N, N m at the TCP, tool frame) and a stiffness stage in the
    model, the deflection it predicts is added (the loaded TCP).
    """
    stages = stored.stages()
    q_effective = q
    for stage in stages:
        q_effective = stage.correct_joints(stored.robot, q_effective)
    chain = next(s for s in stages if isinstance(s, GeometryStage))
    p = chain.position(q_effective)
    for stage in stages:
        offset = stage.tcp_offset(q, temperature=temperature, wrench=wrench)
        if offset is not None:
            p = p + offset.to(p)
    return p


def registered_frame(stored: StoredModel, data: Measurements) -> torch.Tensor:
    """``T_instrument_base`` ``(4, 4)`` of ``stored`` re-fitted to ``data``'s positions (``evaluate --register``):
    the rigid transform that best puts the model's predicted points on the measured ones, after the model's frame."""
    predicted = predict_positions(stored, data.q, data.temperature, data.wrench)
    return rigid_registration(predicted, data.position) @ stored.model.instrument_from_base(stored.x)


def held_out_errors(stored: StoredModel, data: Measurements, *, register: bool = False, residual: bool = True) -> torch.Tensor:
    """``measured - predicted`` (instrument frame, m) of a stored model on ``data``.

    ``register``: first re-fit only the rigid instrument frame (Kabsch, its exact least-squares
    optimum), for data measured with the instrument elsewhere. ``residual=False`` scores the
    model without its learned head.
    """
    if residual:
        predicted = predict_positions(stored, data.q, data.temperature, data.wrench)
    else:
        predicted = stored.model.tcp_position(model_joints(stored, data.q), stored.x)
    return registered_errors(predicted, data.position) if register else data.position - predicted


