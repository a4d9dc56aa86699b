"""The prior's strength chosen by evidence: marginal likelihood, or the fit's grouped cross-validation.

Candidates, simplest first: the nominal robot (MDH table at the prior, instrument frame and tool
fitted: "do not calibrate"), then the prior with every MDH sigma scaled by each of ``scales``
(tight to loose).

:func:`evidence_prior_scales` (the default, ``prior_scale=auto``): each candidate is fitted once on
all poses, each warm-started from the tighter one's fit, and scored by its log marginal likelihood
(:func:`~torchcal.identify.prior.log_evidence`, the model linearised at the MAP); the most probable
wins, the simpler one when within :data:`EVIDENCE_TIE` nats. Cost: one fit per candidate.

:func:`cross_validate_prior_scales` (``prior_scale=cv``): each candidate is fitted on every fold's
training part (geometry only) and scored on the held-out regions;
:func:`~torchcal.model_selection.compare.compare_candidates` keeps the simplest within noise of
the best. Cost: one fit per candidate and fold. ``scripts/bench_prior.py`` compares the two
choices on twins and real sets (docs/prior.md).
"""

from __future__ import annotations

import hashlib
import math
import warnings
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from torchcal.core.errors import IdentifiabilityWarning
from torchcal.data.folds import Folds
from torchcal.data.measurements import Measurements
from torchcal.identify.prior import PriorSpec
from torchcal.model_selection.compare import Candidate, Comparison, compare_candidates

#: Tolerance scales the selection compares (besides the nominal robot).
PRIOR_SCALES = (0.25, 1.0, 4.0, 16.0)
#: Log-evidence differences below this (nats; a Bayes factor of 3, "barely worth mentioning") go to
#: the simpler candidate.
EVIDENCE_TIE = math.log(3.0)


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


def evidence_prior_scales(fitter: Callable[[PriorSpec], Callable], base: PriorSpec, data: Measurements,
                          scales: tuple[float, ...] = PRIOR_SCALES, progress=None) -> tuple[PriorSpec, dict, object]:
    """Choose the prior's scale by the log evidence of each candidate's fit on all of ``data``.

    ``fitter(spec)(data, start=None) -> CalibrationResult`` (a MAP fit with ``log_evidence``; ``start``
    a fit to warm-start from). Returns the chosen spec, its :func:`selection_record`-like record and
    the chosen candidate's fit on all poses (a warm start for every later fit with that prior).
    """
    specs = scale_candidates(base, scales)
    rows: list[dict] = []
    fits: dict[str, object] = {}
    previous = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        for spec in specs:
            if progress is not None:
                progress(f"prior strength by evidence: {spec.label()}")
            result = fitter(spec)(data, start=previous)
            previous = fits[spec.label()] = result
            rows.append({"name": spec.label(), "log_evidence": float(result.log_evidence),
                         "noise_sigma_mm": float(result.noise_sigma_m) * 1e3, "detail": _detail(spec)})
    best = max(r["log_evidence"] for r in rows)
    # simplest first: the first candidate within the tie margin of the best
    chosen_row = next(r for r in rows if r["log_evidence"] >= best - EVIDENCE_TIE)
    chosen = next(s for s in specs if s.label() == chosen_row["name"])
    for r in rows:
        r["delta"] = r["log_evidence"] - best
        r["verdict"] = "chosen" if r is chosen_row else ""
    top = max(rows, key=lambda r: r["log_evidence"])
    reason = ("the most probable" if chosen_row is top else
              f"the simplest within {EVIDENCE_TIE:.2f} nats of the most probable ({top['name']})")
    protocol = (f"log marginal likelihood (evidence) of each candidate's MAP fit on all {len(data)} poses, "
                "the model linearised at the fit")
    table = "\n".join([f"{'candidate':<14} {'log evidence':>14} {'vs best':>9} {'noise sigma':>12}  prior"]
                      + [f"{r['name']:<14} {r['log_evidence']:>14.2f} {r['delta']:>9.2f} {r['noise_sigma_mm']:>9.4f} mm  "
                         f"{r['detail']}{'  <- ' + r['verdict'] if r['verdict'] else ''}" for r in rows])
    record = {
        "method": "evidence",
        "protocol": protocol,
        "candidates": [{"name": r["name"], "log_evidence": r["log_evidence"], "delta_log_evidence": r["delta"],
                        "noise_sigma_mm": r["noise_sigma_mm"], "verdict": r["verdict"]} for r in rows],
        "chosen": chosen.label(),
        "scale": chosen.scale,
        "reason": reason,
        "table": table,
    }
    return chosen, record, fits[chosen.label()]


def selection_summary(record: dict) -> str:
    """One line of a selection record: protocol, each candidate's score, the choice and why."""
    if record.get("method") == "evidence":
        scores = ", ".join(f"{c['name']} {c['delta_log_evidence']:+.1f}" for c in record["candidates"])
        what = "log evidence vs the best"
    else:
        scores = ", ".join(f"{c['name']} {c['cv_rms_mm']:.4f} mm" for c in record["candidates"])
        what = "CV RMS"
    return f"prior scale chosen by {record['protocol']} ({what}): {scores} -> {record['chosen']} ({record['reason']})"


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
        "method": "cv",
        "protocol": comparison.protocol,
        "candidates": [{"name": r["name"], "cv_rms_mm": r["cv_rms_mm"], "verdict": r.get("verdict", "")}
                       for r in comparison.rows],
        "chosen": chosen.label(),
        "scale": chosen.scale,
        "reason": comparison.reason,
        "table": comparison.format_table(),
    }
