"""The prior's strength chosen by evidence: the fit's grouped cross-validation over tolerance scales.

Candidates, simplest first: the nominal robot (MDH table at the prior, instrument frame and tool
fitted: "do not calibrate"), then the prior with every MDH sigma scaled by each of ``scales``
(tight to loose). Each is fitted on every fold's training part (geometry only) and scored on the
held-out regions; :func:`~torchcal.model_selection.compare.compare_candidates` keeps the simplest
within noise of the best. The same folds then judge the structure and the heads.
"""

from __future__ import annotations

import hashlib
import warnings
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from torchcal.core.errors import IdentifiabilityWarning
from torchcal.data.folds import Folds
from torchcal.data.measurements import Measurements
from torchcal.identify.prior import PriorSpec
from torchcal.model_selection.compare import Candidate, Comparison, compare_candidates

#: Tolerance scales the cross-validation compares (besides the nominal robot).
PRIOR_SCALES = (0.25, 1.0, 4.0, 16.0)


def scale_candidates(base: PriorSpec, scales: tuple[float, ...] = PRIOR_SCALES) -> list[PriorSpec]:
    """The nominal robot, then ``base`` with each scale (simplest first)."""
    return [replace(base, scale=0.0), *(replace(base, scale=float(s)) for s in sorted(scales))]


def cross_validate_prior_scales(data: Measurements, fitter: Callable[[PriorSpec], Callable], base: PriorSpec,
                                folds: Folds, scales: tuple[float, ...] = PRIOR_SCALES,
                                progress=None) -> tuple[PriorSpec, Comparison, dict]:
    """Score every candidate prior on ``folds``; ``fitter(spec)(train) -> CalibrationResult`` (geometry).

    Returns the chosen spec, the comparison, and the per-fold fits of the chosen spec keyed by the
    training part (:func:`fold_key`), so the structure cross-validation can reuse them.
    """
    specs = scale_candidates(base, scales)
    n = len(data)
    errors = {s.label(): np.zeros(n) for s in specs}
    fits: dict[str, dict[str, object]] = {s.label(): {} for s in specs}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        for f, (train_idx, test_idx) in enumerate(folds.splits()):
            if progress is not None:
                progress(f"cross-validating the prior's scale: fold {f + 1} of {folds.k}")
            train, test = data.subset(train_idx), data.subset(test_idx)
            for spec in specs:
                result = fitter(spec)(train)
                predicted = result.model.tcp_position(test.q.to(result.x.device), result.x)
                errors[spec.label()][test_idx] = (test.position - predicted.cpu()).norm(dim=-1).detach().numpy() * 1e3
                fits[spec.label()][fold_key(train)] = result
    candidates = [Candidate(s.label(), errors[s.label()], detail=_detail(s)) for s in specs]
    comparison = compare_candidates(candidates, folds.units(), folds.description)
    chosen = next(s for s in specs if s.label() == comparison.chosen)
    return chosen, comparison, fits[chosen.label()]


def _detail(spec: PriorSpec) -> str:
    if spec.nominal:
        return "MDH table at the prior; frame and tool fitted"
    t = spec.tolerances
    return (f"sigma {t.length_mm * spec.scale:.3g} mm, {t.angle_deg * spec.scale:.3g} deg, "
            f"offsets {t.joint_offset_deg * spec.scale:.3g} deg")


def fold_key(train: Measurements) -> str:
    """A key of a training part (its joints), to reuse a fold's fit."""
    return hashlib.sha256(train.q.detach().cpu().numpy().tobytes()).hexdigest()


def selection_record(comparison: Comparison, chosen: PriorSpec) -> dict:
    """What ``calibration.json`` keeps of the choice: protocol, per-candidate CV RMS, the choice and why."""
    return {
        "protocol": comparison.protocol,
        "candidates": [{"name": r["name"], "cv_rms_mm": r["cv_rms_mm"], "verdict": r.get("verdict", "")}
                       for r in comparison.rows],
        "chosen": chosen.label(),
        "scale": chosen.scale,
        "reason": comparison.reason,
        "table": comparison.format_table(),
    }
