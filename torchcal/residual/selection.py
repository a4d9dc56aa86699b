"""Fit candidate heads and keep one only where it beats "no residual" on validation."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcal.residual.base import ResidualHead, rms


@dataclass
class Selection:
    """The kept head (or ``None``), validation RMS of every candidate, and why."""

    head: ResidualHead | None
    validation_rms: dict[str, float]
    baseline_rms: float
    decision: str


def select_head(candidates: list[ResidualHead], x_train, y_train, x_val, y_val, *, margin: float = 0.05) -> Selection:
    """Fit each candidate; keep the best if its validation RMS is below ``(1 - margin)`` of zero's."""
    baseline = rms(y_val)
    scores: dict[str, float] = {}
    best, best_score = None, float("inf")
    for head in candidates:
        head.fit(x_train, y_train, x_val, y_val)
        score = rms(head.predict(x_val) - y_val)
        scores[head.name] = score
        if score < best_score:
            best, best_score = head, score
    if best is not None and best_score < (1.0 - margin) * baseline:
        gain = 100.0 * (1.0 - best_score / baseline)
        decision = (f"residual head '{best.name}' kept: validation RMS {best_score:.4f} mm vs {baseline:.4f} mm "
                    f"without it ({gain:.0f} % lower)")
        return Selection(best, scores, baseline, decision)
    tried = ", ".join(f"{k} {v:.4f} mm" for k, v in scores.items())
    decision = (f"no residual head kept: none beat geometry alone on validation by {margin * 100:.0f} % "
                f"(geometry {baseline:.4f} mm; {tried})")
    return Selection(None, scores, baseline, decision)
