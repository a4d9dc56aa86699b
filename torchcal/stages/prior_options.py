"""The prior of a geometry fit from its options, and what a model folder keeps of prior and posterior.

``FitConfig.prior``: ``tolerance`` (default; manufacturing tolerances, :mod:`torchcal.identify.prior`),
``none`` (the rank cut: parameters the data cannot separate fixed at nominal, everything else free)
or a model folder (an earlier calibration, its parameters and covariance as the prior mean and
covariance). ``prior_scale``: ``auto`` (marginal likelihood) or ``cv`` (grouped cross-validation), both
:mod:`torchcal.model_selection.prior_scale`, ``nominal`` or a number multiplying the MDH sigmas. ``tolerance_*`` override the robot file's
``calibration_prior`` and the built-in defaults.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from torchcal.core.errors import DataError
from torchcal.identify.prior import (
    EarlierModel,
    PriorSpec,
    beyond_tolerance_warning,
    prior_table,
    resolve_tolerances,
    taught_summary,
)
from torchcal.kinematics.robot import RobotModel
from torchcal.stages.store import load_model

TOLERANCE_OPTIONS = {
    "tolerance_length_mm": "length_mm",
    "tolerance_angle_deg": "angle_deg",
    "tolerance_joint_offset_deg": "joint_offset_deg",
    "tolerance_tool_mm": "tool_mm",
    "tolerance_tool_deg": "tool_deg",
}


def parse_scale(value: str | float) -> float | str:
    """``auto`` -> ``"evidence"``, ``cv`` -> ``"cv"`` (chosen by the data), ``nominal`` -> 0, else a number >= 0."""
    text = str(value).strip().lower()
    if text == "auto":
        return "evidence"
    if text == "cv":
        return "cv"
    if text == "nominal":
        return 0.0
    try:
        scale = float(text)
    except ValueError:
        raise DataError(f"prior_scale must be auto, cv, nominal or a number >= 0, got {value!r}") from None
    if not math.isfinite(scale) or scale < 0:
        raise DataError(f"prior_scale must be auto, cv, nominal or a number >= 0, got {value!r}")
    return scale


def base_spec(robot: RobotModel, config) -> PriorSpec | None:
    """The prior of ``config`` at scale 1 (``None``: ``prior=none``, or ``method=lasso`` which selects its own support)."""
    if str(config.prior) == "none" or config.method == "lasso":
        return None
    options = {key: getattr(config, opt) for opt, key in TOLERANCE_OPTIONS.items()}
    tolerances = resolve_tolerances(robot.source, options)
    earlier = None if str(config.prior) == "tolerance" else earlier_model(Path(config.prior), robot)
    return PriorSpec(tolerances=tolerances, scale=1.0, earlier=earlier)


def earlier_model(folder: Path, robot: RobotModel) -> EarlierModel:
    """An earlier model folder as prior: its parameters and their covariance (checked against ``robot``)."""
    if not folder.is_dir():
        raise DataError(f"prior={folder}: neither 'tolerance', 'none' nor a model folder")
    stored = load_model(folder)
    if stored.robot.dof != robot.dof:
        raise DataError(f"prior={folder}: a model of a {stored.robot.dof}-joint robot, this robot has {robot.dof}")
    return EarlierModel(x=stored.x.detach().cpu().to(torch.float64), indices=stored.free.detach().cpu(),
                        covariance=stored.covariance.detach().cpu().to(torch.float64), label=str(folder))


def prior_metadata(result) -> dict | None:
    """``calibration.json`` ``prior``: what the prior was, how its scale was chosen, and per parameter prior vs posterior."""
    if result.prior is None:
        return None
    layout = result.model.layout
    rows = prior_table(list(layout.names), layout.is_angle().tolist(), result.prior, result.x, result.covariance)
    return {
        "source": result.prior.spec.describe(),
        "scale": result.prior.spec.scale,
        "tolerances": {k: getattr(result.prior.spec.tolerances, k) for k in TOLERANCE_OPTIONS.values()},
        "tolerance_band_sigmas": 3.0,
        "noise_sigma_mm": None if result.noise_sigma_m is None else result.noise_sigma_m * 1e3,
        "selection": result.prior_selection,
        "summary": taught_summary(rows),
        "parameters": rows,
    }


def prior_warning(result) -> str | None:
    """The warning naming parameters beyond their tolerance (``None`` when none is, or without a prior)."""
    if result.prior is None:
        return None
    layout = result.model.layout
    return beyond_tolerance_warning(prior_table(list(layout.names), layout.is_angle().tolist(), result.prior,
                                                result.x, result.covariance))
