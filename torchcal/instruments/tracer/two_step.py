"""Robot calibration from laser-tracer lengths in two steps.

1. Self-calibrating multilateration (:func:`~torchcal.instruments.tracer.multilateration.multilaterate`) of every pose
   seen by at least three stations gives points, stations and dead paths with their covariance,
   in the *points* gauge (the uncertainty of the point cloud's shape), fitted to the nominal TCP
   points so the coordinates are near the robot ``base`` frame.
2. The tracker pipeline (:func:`~torchcal.identify.calibrate.calibrate`) identifies the robot from
   the points, whitened by their 3x3 covariance blocks: residual ``L_i^-1 (P_i - FK_i(x))`` with
   ``C_i = L_i L_i^T``. The multilateration frame plays the role of the tracker frame, so the
   ``base_*`` parameters are estimated as usual. Correlations *between* points (through the
   shared stations) are left out: this is what "points with covariances as weights" can use.

Poses seen by fewer than three stations cannot be located and are left out of this method.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace

import torch

from torchcal.core.errors import DataError
from torchcal.data.measurements import Measurements
from torchcal.identify.base import Identifier
from torchcal.identify.calibrate import CalibrationResult, calibrate
from torchcal.instruments.tracer.data import TracerData
from torchcal.instruments.tracer.lengths import LengthSigma
from torchcal.instruments.tracer.locate import locate_pose_candidates
from torchcal.instruments.tracer.multilateration import MultilaterationResult
from torchcal.kinematics.error_model import DEFAULT_PARALLEL_THRESHOLD_DEG, ErrorModel
from torchcal.kinematics.robot import RobotModel


@dataclass
class TracerTwoStepResult:
    """The multilateration and the whitened robot fit.

    Attributes:
        multilateration: step 1 (points gauge covariance, coordinates near ``base``).
        calibration: step 2; its ``model.T_reference`` maps ``base`` into the multilateration frame.
        rows: indices of the poses that were located (and used by step 2).
        located_rows: indices of the poses passed to the multilateration (seen by >= 3 stations);
            ``multilateration`` rows refer to them.
        point_residual_rms_m: RMS 3-D distance between the points and the calibrated model, m.
        stations / dead_paths: ``(m, 3)`` and ``(m,)``, m, stations in the calibrated ``base`` frame.
    """

    multilateration: MultilaterationResult
    calibration: CalibrationResult
    rows: torch.Tensor
    located_rows: torch.Tensor
    point_residual_rms_m: float
    stations: torch.Tensor
    dead_paths: torch.Tensor

    @property
    def station_sigmas(self) -> torch.Tensor:
        """``(m, 3)`` station sigmas, m, rotated into ``base`` (points gauge of step 1)."""
        rot = self.calibration.model.T_reference[:3, :3].to(self.stations)
        cov = rot.T @ self.multilateration.station_covariances @ rot * self.variance_factor
        return cov.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()

    @property
    def dead_path_sigmas(self) -> torch.Tensor:
        return self.multilateration.dead_path_sigmas * self.variance_factor**0.5

    @property
    def variance_factor(self) -> float:
        """A-posteriori variance factor of the lengths (1 when the sigma model is right)."""
        vf = self.multilateration.variance_factor
        return vf if vf == vf else 1.0


def _fit_points(robot, data, ml, rows, located, identifier, parallel_threshold_deg, device):
    """Step 2 for one multilateration: ``(result, points, whitening, scale)``, ``None`` if singular.

    ``result.sigma_residual_m`` is the unitless a-posteriori sigma of unit weight.
    """
    # a-posteriori where the lengths scatter more than the model says (robot repeatability)
    vf = ml.variance_factor if math.isfinite(ml.variance_factor) else 1.0
    cov = ml.point_covariances[located] * max(vf, 1.0)
    try:
        whitening = torch.linalg.inv(torch.linalg.cholesky(cov))
    except RuntimeError:
        return None
    # Whitened residuals carry no unit; scaled back to the points' typical sigma they keep the
    # size of a tracker problem, for which the identifiers' damping and tolerances are tuned.
    scale = float(cov.diagonal(dim1=-2, dim2=-1).mean().sqrt())
    whitening = whitening * scale
    points = Measurements(q=data.q[rows][located], position=ml.points[located], source=data.source, sha256=data.sha256)
    result = calibrate(robot, points, identifier=identifier, parallel_threshold_deg=parallel_threshold_deg,
                       device=device, whitening=whitening)
    result.sigma_residual_m /= scale
    return result, points, whitening, scale


def calibrate_two_step(
    robot: RobotModel,
    data: TracerData,
    *,
    sigma: LengthSigma | None = None,
    identifier: Identifier | None = None,
    parallel_threshold_deg: float = DEFAULT_PARALLEL_THRESHOLD_DEG,
    device: str | torch.device = "cpu",
) -> TracerTwoStepResult:
    """Multilaterate, then identify the robot from the whitened points (see module docstring).

    Args:
        sigma: length noise model (``None``: the default model). It weights the lengths; the
            reported station and dead-path sigmas are scaled by the multilateration's a-posteriori
            variance factor, and the robot covariance by that of step 2, so robot repeatability
            (which the length model does not know) is accounted for.
        identifier: robot identifier of step 2 (default Levenberg-Marquardt).
    """
    data = data.to(device)
    nominal = ErrorModel(robot, device=device)
    p0 = nominal.tcp_position(data.q, nominal.nominal_vector())
    candidates, rows = locate_pose_candidates(data.lengths, p0, sigma or LengthSigma())
    best = None
    for ml in candidates:
        located = torch.isfinite(ml.points).all(-1)  # whole points rejected as gross errors are NaN
        fitted = _fit_points(robot, data, ml, rows, located, identifier, parallel_threshold_deg, device)
        # With little redundancy a wrong geometry can fit the lengths as well as the right one:
        # the robot model, which a wrong point cloud does not fit, decides.
        if fitted is not None and (best is None or fitted[0].sigma_residual_m < best[0].sigma_residual_m):
            best = (*fitted, ml, located)
    if best is None:
        raise DataError("no multilateration of these lengths gives points with a regular covariance; "
                        "remove poses seen by few stations", path=data.source)
    result, points, whitening, scale, ml, located = best
    # Analyzed at the nominal tool (on axis 6), alpha6 and a6 look confounded with d5 and theta5; at
    # the fitted, slightly off-axis tool they are separable by a fraction of a micrometre, which
    # multilaterated points resolve. So the fit is repeated with the fitted tool as nominal.
    tool = result.x[result.model.layout.tool_slice][:3].detach().cpu()
    again = calibrate(replace(robot, tool=tool), points, identifier=identifier, parallel_threshold_deg=parallel_threshold_deg,
                      device=device, whitening=whitening)
    again.sigma_residual_m /= scale
    if len(again.free) > len(result.free) and again.sigma_residual_m <= result.sigma_residual_m:
        result = again
    if result.sigma_residual_m > 10.0:
        result.notes.append(
            f"the multilaterated points fit the robot at {result.sigma_residual_m:.0f} times their own sigma: the "
            f"lengths alone hardly fix the geometry (redundancy {ml.dof}); prefer tracer_method=joint"
        )
        warnings.warn(result.notes[-1], stacklevel=2)
    t_ref = result.model.T_reference.to(ml.stations)
    stations = (ml.stations - t_ref[:3, 3]) @ t_ref[:3, :3]  # multilateration frame -> base
    residual = points.position - result.model.tcp_position(points.q, result.x)
    rms = float(residual.pow(2).sum(-1).mean().sqrt())
    return TracerTwoStepResult(ml, result, rows[located], rows, rms, stations, ml.dead_paths)
