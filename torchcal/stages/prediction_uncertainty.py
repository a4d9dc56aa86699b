"""Per-pose prediction uncertainty of a model folder: the error to expect at poses never measured.

A model's error at a new pose has two parts:

* the **parameter uncertainty**: the fit's covariance propagated to the point by the point
  Jacobian, ``J Sigma J^T``;
* the **model discrepancy**: what the model cannot explain (unmodelled physics, the
  measurement's noise). It is estimated from the out-of-fold errors of the fit's own grouped
  cross-validation (whole configuration regions held out, the folds of model selection), so it
  is the scatter of poses the fit did not see, not the residual of the poses it was fitted to.

Two ways to turn them into a 95 % region per pose are calibrated on the same out-of-fold errors
and kept in ``uncertainty.json``; ``FitConfig.uncertainty`` names the one reported:

* ``gaussian``: the error is ``N(0, J Sigma J^T + sigma_d^2 I)`` with
  ``sigma_d^2 = max(0, mean |e_cv|^2 / 3 - mean tr(J Sigma J^T) / 3)``; the region is the ball that
  holds 95 % of it (its radius from seeded Gaussian draws).
* ``conformal``: normalised scores ``s = |e_cv| / sigma_hat`` with
  ``sigma_hat^2 = tr(J Sigma J^T) / 3 + sigma_d^2``; the region is the ball of radius
  ``q sigma_hat``, ``q`` the split-conformal 95 % quantile of the scores (no distribution assumed;
  the coverage holds as far as new poses resemble a held-out configuration region).

Units: millimetres in the file and in what is returned; the frames are those of the measured
points (the instrument frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchcal.core.errors import ModelError
from torchcal.core.folder import write_member_json
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.identify.uncertainty import (
    conformal_factor,
    gaussian_radius_samples,
    point_covariance,
)
from torchcal.stages.files import read_json_member

UNCERTAINTY_FILE = "uncertainty.json"
FORMAT = "torchcal-uncertainty/1"
METHODS = ("conformal", "gaussian")
LEVEL = 0.95
#: Gaussian draws per pose for the radius quantiles (the standard error of a 95 % point from 256
#: draws is about 3 % of the radius).
DRAWS = 256


@dataclass(frozen=True)
class ErrorCalibration:
    """The calibrated uncertainty of one model folder (mm).

    Attributes:
        method: the one reported (``conformal`` or ``gaussian``).
        discrepancy_sigma_mm: per-coordinate sigma of the model discrepancy (noise included).
        conformal_q: the 95 % split-conformal quantile of the normalised out-of-fold scores.
        score_quantiles: the scores' 0, 1, ..., 100 % points (a set's predicted distribution).
        cv_rms_mm: RMS of the out-of-fold 3-D errors it was calibrated on.
        n_poses: how many out-of-fold errors.
        protocol: the cross-validation that produced them.
        shape_n_poses: how many out-of-fold errors the scores' shape (``conformal_q``,
            ``score_quantiles``) was calibrated on: ``n_poses``, or an ancestor's where an update kept
            it; ``None`` where a file of an earlier version did not record an ancestor's count.
    """

    method: str
    discrepancy_sigma_mm: float
    conformal_q: float
    score_quantiles: tuple[float, ...]
    cv_rms_mm: float
    n_poses: int
    protocol: str
    shape_n_poses: int | None = None

    def to_dict(self) -> dict:
        return {"format": FORMAT, "method": self.method, "level": LEVEL,
                "discrepancy_sigma_mm": self.discrepancy_sigma_mm, "conformal_q": self.conformal_q,
                "score_quantiles": list(self.score_quantiles), "cv_rms_mm": self.cv_rms_mm,
                "n_poses": self.n_poses, "protocol": self.protocol, "shape_n_poses": self.shape_n_poses}

    @classmethod
    def from_dict(cls, d: dict, path: Path) -> ErrorCalibration:
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise ModelError(f"{path}: not a {FORMAT} file")
        if d.get("method") not in METHODS:
            raise ModelError(f"{path}: method must be one of {', '.join(METHODS)}, got {d.get('method')!r}")
        numbers = {k: d.get(k) for k in ("discrepancy_sigma_mm", "conformal_q", "cv_rms_mm")}
        for key, value in numbers.items():
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ModelError(f"{path}: {key} must be a finite number >= 0, got {value!r}")
        quantiles = d.get("score_quantiles")
        if (not isinstance(quantiles, list) or len(quantiles) < 2
                or not all(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0 for v in quantiles)):
            raise ModelError(f"{path}: score_quantiles must be a list of finite numbers >= 0")
        shape = d.get("shape_n_poses", None if "kept from the parent" in str(d.get("protocol", "")) else d.get("n_poses"))
        return cls(d["method"], float(d["discrepancy_sigma_mm"]), float(d["conformal_q"]),
                   tuple(float(v) for v in quantiles), float(d["cv_rms_mm"]), int(d.get("n_poses", 0)),
                   str(d.get("protocol", "")), int(shape) if isinstance(shape, int) else None)


@dataclass(frozen=True)
class PosePrediction:
    """Predicted error distribution at a set of poses (mm).

    Attributes:
        p95_mm: ``(B,)`` radius of each pose's 95 % region (the predicted 95th percentile of its
            3-D error).
        set_p95_mm: the predicted 95th percentile of the 3-D error over the whole set.
        sigma_mm: ``(B,)`` per-coordinate sigma of each pose's predicted error.
        method: which calibration produced them.
        pooled_mm: draws of the set's predicted 3-D error distribution (to pool sets).
        protocol: the cross-validation the calibration was made on (its :attr:`ErrorCalibration.protocol`).
    """

    p95_mm: torch.Tensor
    set_p95_mm: float
    sigma_mm: torch.Tensor
    method: str
    pooled_mm: torch.Tensor
    protocol: str = ""


def point_jacobian(model, x: torch.Tensor, free: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
    """``(B, 3, K)`` derivative of the TCP position (m) with respect to the estimated parameters."""
    _, jac = model.position_jacobian(joints, x, free, method="analytic")
    return jac


def calibrate_errors(point_jac: torch.Tensor, covariance: torch.Tensor, cv_errors_mm: np.ndarray, protocol: str,
                     method: str = "conformal") -> ErrorCalibration:
    """Calibrate both methods on out-of-fold 3-D errors ``cv_errors_mm (n,)`` at the training poses.

    ``point_jac (n, 3, K)`` (m per parameter unit) and ``covariance (K, K)`` are the full model's at
    the same poses.
    """
    if method not in METHODS:
        raise ValueError(f"uncertainty method must be one of {', '.join(METHODS)}, got {method!r}")
    e = torch.as_tensor(np.asarray(cv_errors_mm, dtype=np.float64))
    if len(e) == 0 or not torch.isfinite(e).all():
        raise ValueError("out-of-fold errors must be finite and not empty")
    param_var = _parameter_var_mm2(point_jac, covariance)
    discrepancy_var = max(0.0, float(e.pow(2).mean()) / 3 - float(param_var.mean()))
    sigma_hat = (param_var + discrepancy_var).clamp_min(1e-30).sqrt()
    scores = e / sigma_hat
    levels = torch.linspace(0, 1, 101, dtype=torch.float64)
    quantiles = torch.quantile(scores, levels)
    return ErrorCalibration(method, discrepancy_var**0.5, conformal_factor(scores, LEVEL),
                            tuple(float(v) for v in quantiles), float(e.pow(2).mean().sqrt()), len(e), protocol,
                            shape_n_poses=len(e))


def _parameter_var_mm2(point_jac: torch.Tensor, covariance: torch.Tensor) -> torch.Tensor:
    """Per-coordinate variance ``(B,)`` (mm^2) of each point from the parameter covariance."""
    cov = point_covariance(point_jac, covariance.to(point_jac), 0.0)
    return cov.diagonal(dim1=-2, dim2=-1).sum(-1) / 3 * 1e6


def predict(calibration: ErrorCalibration, point_jac: torch.Tensor, covariance: torch.Tensor,
            method: str | None = None) -> PosePrediction:
    """The predicted error distribution at poses with point Jacobians ``point_jac (B, 3, K)``."""
    method = method or calibration.method
    cov = point_covariance(point_jac, covariance.to(point_jac), 0.0) * 1e6  # mm^2
    discrepancy_var = calibration.discrepancy_sigma_mm**2
    sigma = (cov.diagonal(dim1=-2, dim2=-1).sum(-1) / 3 + discrepancy_var).clamp_min(1e-30).sqrt()
    if method == "gaussian":
        eye = torch.eye(3, dtype=cov.dtype, device=cov.device)
        radii = gaussian_radius_samples(cov + discrepancy_var * eye, DRAWS)
        p95 = torch.quantile(radii, LEVEL, dim=1)
        pooled = radii.flatten()
    elif method == "conformal":
        p95 = calibration.conformal_q * sigma
        pooled = (sigma[:, None] * torch.tensor(calibration.score_quantiles, dtype=sigma.dtype)).flatten()
    else:
        raise ValueError(f"uncertainty method must be one of {', '.join(METHODS)}, got {method!r}")
    pooled = subsample(pooled)
    set_p95 = float(torch.quantile(pooled, LEVEL)) if len(pooled) else float("nan")
    return PosePrediction(p95, set_p95, sigma, method, pooled, calibration.protocol)


def subsample(values: torch.Tensor, limit: int = 1_000_000) -> torch.Tensor:
    """At most ``limit`` of ``values`` (seeded): ``torch.quantile``'s input limit, the 95 % point kept."""
    if len(values) <= limit:
        return values
    gen = torch.Generator().manual_seed(0)
    return values[torch.randint(len(values), (limit,), generator=gen)]


def score(prediction: PosePrediction, errors_m: torch.Tensor, protocol: str) -> dict:
    """What a scored set says about the prediction: coverage and predicted against observed p95."""
    observed = errors_m.norm(dim=-1).detach().cpu().double() * 1e3
    p95 = prediction.p95_mm.detach().cpu().double()
    return {
        "method": prediction.method,
        "coverage_95": float((observed <= p95).double().mean()) if len(observed) else float("nan"),
        "predicted_p95_mm": prediction.set_p95_mm,
        "observed_p95_mm": float(torch.quantile(observed, LEVEL)) if len(observed) else float("nan"),
        "per_pose_predicted_p95_mm": p95.tolist(),
        "protocol": protocol,
    }


def write_uncertainty(folder: Path, calibration: ErrorCalibration) -> None:
    write_member_json(Path(folder), UNCERTAINTY_FILE, calibration.to_dict())


def load_uncertainty(folder: Path) -> ErrorCalibration | None:
    """The folder's calibration, or ``None`` for a model folder written without one."""
    path = Path(folder) / UNCERTAINTY_FILE
    if not path.is_file():
        return None
    return ErrorCalibration.from_dict(read_json_member(path), path)


def stored_prediction(stored, q: torch.Tensor, method: str | None = None) -> PosePrediction | None:
    """The prediction of a loaded model folder at joints ``q`` (rad), or ``None`` without a calibration."""
    calibration = load_uncertainty(stored.folder)
    if calibration is None:
        return None
    joints = JointSpaceErrors.from_metadata(stored.metadata).effective_joints(stored.robot, q)
    jac = point_jacobian(stored.model, stored.x, stored.free, joints)
    return predict(calibration, jac, stored.covariance, method)
