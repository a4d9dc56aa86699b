"""Scoring a stored model on tracker points: held-out errors, leakage, what the compensator leaves."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from torchcal.compensate.compensator import CompensatorGraph
from torchcal.compensate.export_checks import regular_poses
from torchcal.compensate.production_tcp import correction_extent, production_view, tcp_transform
from torchcal.config.schema import FitConfig
from torchcal.core.errors import DataError
from torchcal.core.metrics import iso9283_repeated, position_metrics
from torchcal.data.measurements import Measurements, count_configurations, load_measurements
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.model_selection.leakage import distances, far_mask, leakage_report
from torchcal.stages.foreign_data import refuse_foreign_file
from torchcal.stages.geometry import NOMINAL_PROTOCOL, held_out_errors, nominal_fit
from torchcal.stages.orientation import (
    OrientationErrors,
    model_orientation_errors,
    nominal_orientation_errors,
    orientation_source_of,
    refuse_implausible,
)
from torchcal.stages.prediction_uncertainty import score as score_uncertainty
from torchcal.stages.prediction_uncertainty import stored_prediction
from torchcal.stages.store import StoredModel, load_model

#: ``evaluate --register``: fewer distinct configurations are refused; fewer than the advised give a warning.
REGISTER_MIN_POSES, REGISTER_ADVISED_POSES = 4, 10
#: The nominal robot's frame and tool (9 parameters) fitted to fewer distinct configurations is no comparison.
NOMINAL_MIN_CONFIGURATIONS = 5


@dataclass
class Scored:
    """A model folder scored on a file: the metrics of ``evaluate`` and what a report needs besides.

    ``errors``: ``measured - predicted`` ``(n, 3)`` of the model as delivered, instrument frame, m.
    ``nominal_errors``, ``nominal_frame``: the same for the nominal robot with its instrument frame
    and tool fitted to the file (:func:`~torchcal.stages.geometry.nominal_fit`), and that frame
    ``T_instrument_base`` ``(4, 4)``. ``orientation``: where the file measures the tool's
    orientation, the model's and the nominal robot's angles (``None`` otherwise). A report reuses
    them instead of scoring the file again.
    """

    stored: StoredModel
    data: Measurements
    errors: torch.Tensor
    metrics: dict[str, Any]
    nominal_errors: torch.Tensor
    nominal_frame: torch.Tensor
    orientation: tuple[OrientationErrors, OrientationErrors] | None = None


def evaluate(model_dir: str | Path, data_path: str | Path, *, register: bool = False, config: FitConfig | None = None) -> dict:
    """Score a model folder on a measurement file (see the command-line contract)."""
    config = config or FitConfig()
    stored = load_model(model_dir)
    data = load_measurements(data_path, stored.robot, joint_unit=config.joint_unit, length_unit=config.length_unit)
    return score(stored, data, register=register).metrics


def score(stored: StoredModel, data: Measurements, *, register: bool = False, leakage: bool = True,
          corrections: bool = True) -> Scored:
    """The metrics of ``stored`` on ``data`` (mm): errors, ISO 9283 where poses repeat, leakage, the compensator.

    ``leakage``: compare the poses with the training poses (off for the training file itself).
    ``corrections``: the compensator's joint corrections with their 1-sigma (off for the fit's own report:
    ``export`` states them over the training poses; the sigma costs a solve per table parameter).
    """
    warning: str | None = None
    # repeated joints add measurements, not geometry: the frame and tool fits count configurations
    distinct = count_configurations(data.q)
    configurations = f"{distinct} distinct joint configurations" + (f" ({len(data)} poses)" if distinct < len(data) else "")
    if register:
        if distinct < REGISTER_MIN_POSES:
            raise DataError(f"--register fits the instrument frame (6 parameters) to the file's points; {configurations} "
                            f"cannot check it (at least {REGISTER_MIN_POSES}, better {REGISTER_ADVISED_POSES})",
                            path=data.source)
        if distinct < REGISTER_ADVISED_POSES:
            warning = (f"--register fitted 6 frame parameters to {configurations}: the RMS is optimistic; score on "
                       f"{REGISTER_ADVISED_POSES} or more configurations")
            warnings.warn(warning, stacklevel=2)
    errors = held_out_errors(stored, data, register=register)
    refuse_foreign_file(errors, stored, data, register)
    metrics: dict[str, Any] = position_metrics(errors)
    metrics.update({"model": str(stored.folder), "data": str(data.source), "registered": register})
    # the fair 'before' on the same poses: what the uncalibrated robot misses them by
    nominal_errors, nominal_frame, _ = nominal_fit(stored.robot, data)
    before = position_metrics(nominal_errors)
    protocol = NOMINAL_PROTOCOL
    if distinct < NOMINAL_MIN_CONFIGURATIONS:  # 9 parameters (frame and tool) fitted to 3 coordinates per configuration
        protocol += (f"; fitted to only {configurations}: {3 * distinct} coordinates for its 9 parameters, no "
                     "comparison")
        caveat = (f"the nominal robot's frame and tool were fitted to {configurations}: its figure is no comparison; "
                  f"score on {NOMINAL_MIN_CONFIGURATIONS} or more")
        warnings.warn(caveat, stacklevel=2)
        warning = caveat if warning is None else f"{warning}; {caveat}"
    metrics["nominal"] = {**before, "protocol": protocol}
    metrics["nominal_position_rms_mm"] = before["position_rms_mm"]
    angles = None
    if data.rotation is not None:  # the file measures the tool's orientation too: scored alike
        angles = orientation_errors(stored, data, nominal_frame, register=register)
        orientation, worse = orientation_metrics(*angles, stored)
        metrics["orientation"] = orientation
        metrics["orientation_rms_deg"] = orientation["orientation_rms_deg"]
        metrics["nominal_orientation_rms_deg"] = orientation["nominal"]["orientation_rms_deg"]
        if worse is not None:
            warnings.warn(worse, stacklevel=2)
            warning = worse if warning is None else f"{warning}; {worse}"
    # distances to the training poses, once for the coverage split and the leakage report
    measured = distances(stored.robot, stored.training_q, data.q) if stored.training_q is not None else None
    prediction = stored_prediction(stored, data.q)
    if prediction is not None:
        uncertainty = score_uncertainty(prediction, errors, f"{prediction.method}, calibrated on the fit's out-of-fold "
                                        f"errors ({prediction.protocol or 'unknown'})")
        if measured is not None:  # where the poses are far from the training ones, said apart
            uncertainty.update(extrapolation_split(measured, errors, prediction.p95_mm))
        metrics.update({"coverage_95": uncertainty["coverage_95"], "predicted_p95_mm": uncertainty["predicted_p95_mm"],
                        "uncertainty": uncertainty})
    if warning is not None:
        metrics["warnings"] = [warning]
    metrics["iso9283"] = iso9283_repeated(errors, data.q, rows=data.line_numbers)
    if leakage and stored.training_q is not None:
        metrics["leakage"] = leakage_report(stored.robot, stored.training_q, data.q, measured=measured).to_dict()
    metrics["compensator"] = compensator_summary(stored, data.q, errors, corrections=corrections)
    return Scored(stored, data, errors, metrics, nominal_errors, nominal_frame, angles)


def extrapolation_split(measured: tuple, errors: torch.Tensor, p95_mm: torch.Tensor) -> dict:
    """The predicted 95 % regions' coverage apart for the poses far from every training pose and the
    others (``measured``: :func:`~torchcal.model_selection.leakage.distances` of the scored poses):
    the regions are calibrated on poses like the training poses, and far from them promise nothing."""
    d_scored, _, radius = measured
    far_t = torch.from_numpy(far_mask(d_scored, radius))
    inside = errors.norm(dim=-1).detach().cpu().double() * 1e3 <= p95_mm.detach().cpu().double()

    def share(mask: torch.Tensor) -> float | None:
        return float(inside[mask].double().mean()) if bool(mask.any()) else None

    return {"far_radius_mm": radius if math.isfinite(radius) else None, "n_far": int(far_t.sum()), "coverage_95_far": share(far_t),
            "coverage_95_like_training": share(~far_t)}


def orientation_errors(stored: StoredModel, data: Measurements, nominal_frame: torch.Tensor, *,
                       register: bool) -> tuple[OrientationErrors, OrientationErrors]:
    """The model's and the nominal robot's orientation errors on ``data`` (``rx, ry, rz``; :mod:`torchcal.stages.orientation`).

    ``nominal_frame``: ``T_instrument_base`` of the nominal robot fitted to the file's positions.

    Raises:
        DataError: columns even the nominal robot misses by degrees (another angle convention).
    """
    nominal = nominal_orientation_errors(stored.robot, data, nominal_frame)
    refuse_implausible(nominal, data)
    return model_orientation_errors(stored, data, register=register), nominal


def orientation_metrics(model: OrientationErrors, nominal: OrientationErrors, stored: StoredModel) -> tuple[dict, str | None]:
    """The metrics of :func:`orientation_errors`' angles, and a warning when the model's are the
    larger (``None`` otherwise)."""
    orientation = model.metrics()
    orientation["nominal"] = nominal.metrics()
    model_rms, nominal_rms = orientation["orientation_rms_deg"], orientation["nominal"]["orientation_rms_deg"]
    if model_rms <= nominal_rms:
        return orientation, None
    cause = ("its joint-space terms may stand for errors that are not rotations of those joints (docs/prior.md); "
             "compare a geometry-only fit on this file"
             if orientation_source_of(stored.model) == "model" and not JointSpaceErrors.from_metadata(stored.metadata).empty
             else "check that the file's robot, tool and set-up are the fitted ones")
    return orientation, (f"on these poses the model predicts the tool's orientation worse than the nominal robot "
                         f"({model_rms:.4f} against {nominal_rms:.4f} deg RMS), and its compensator turns the tool by "
                         f"what the model predicts: {cause}")


def compensator_summary(stored: StoredModel, q: torch.Tensor, model_errors: torch.Tensor | None = None, *,
                        corrections: bool = True) -> dict:
    """What the default exported compensator (position first) leaves at the joints ``q``, by the model's own account.

    For each pose its command is solved as the exported graph does (no load), and the graph's
    ``residual`` output gives the remaining TCP position error and the tool's orientation
    deviation from the nominal target. Returns the share of poses solved to 1 um (mm and rad
    values below). With the model's errors ``(n, 3)`` (m) on these poses, ``delivered_*_mm`` bound
    what a compensated command leaves: per pose the model's error plus the unsolved part. With
    ``corrections``, also the joint corrections over the poses not near a singularity, with their
    1-sigma from the calibration's uncertainty (:func:`~torchcal.compensate.production_tcp.correction_extent`).

    The graph is the one ``torchcal export`` writes by default: both chains end in the flange
    (:func:`~torchcal.compensate.production_tcp.production_view`), not in the measured point, whose
    fitted probe rotation (a 6-D fit's) the nominal chain does not have.
    """
    stored = production_view(stored, tcp_transform(None, None))
    graph = CompensatorGraph.from_stored(stored)
    with torch.no_grad():
        _, residual = graph.solve(q.to(torch.float64))
    position_mm, turn = residual[:, 0] * 1e3, residual[:, 1]
    extents = {}
    regular = regular_poses(stored.robot, q) if corrections else None
    if regular is not None and len(regular):  # the joint corrections and their uncertainty, as the export states them
        extent = correction_extent(graph, regular, stored)
        extents = {"corrections": {key: extent[key] for key in (
            "n_poses", "largest_joint_correction_deg", "joint", "median_joint_correction_deg",
            "largest_joint_correction_sigma_deg", "median_joint_correction_sigma_deg", "sigma_from")}}
    delivered = {}
    if model_errors is not None:
        bound = model_errors.detach().to(position_mm).norm(dim=-1) * 1e3 + position_mm
        delivered = {"delivered_rms_mm": float(bound.pow(2).mean().sqrt()), "delivered_p95_mm": float(bound.quantile(0.95)),
                     "delivered_max_mm": float(bound.max())}
    return {
        "task": graph.task,
        "iterations": graph.iterations,
        "solved_share": float((position_mm <= 1e-3).double().mean()),
        "unsolved_max_mm": float(position_mm.max()),
        "orientation_deviation_median_rad": float(turn.median()),
        "orientation_deviation_p99_rad": float(turn.quantile(0.99)),
        "orientation_deviation_max_rad": float(turn.max()),
        **delivered,
        **extents,
    }


