"""Fit candidate heads and keep one only where it beats "no residual" on validation.

The validation poses decide and nothing else sees them: a head's own model selection (the
Mayfly search of an MMA-ELM, the early stopping of an MLP) runs on a tuning part split off the
training poses; a head that tunes nothing (plain ELM) fits on all training poses. A search scored on the gate's poses would pass the gate by having fitted their
noise (on 30 real poses an MMA-ELM "won" by 50 % and then doubled the held-out error).

A head is kept when both hold on the validation poses:

* its RMS is below ``(1 - margin)`` of the RMS of predicting zero, and
* the per-pose gain ``d_i = |e_i|^2 - |e_i - h_i|^2`` is positive beyond chance: its mean is
  more than ``z_min`` standard errors above zero (a paired one-sided test; with a handful of
  validation poses even a large apparent gain is not evidence).
"""

from __future__ import annotations

import math
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


def paired_gain_z(y_val: torch.Tensor, predicted: torch.Tensor) -> float:
    """Mean per-pose gain in squared error over its standard error (``inf`` when all equal and positive)."""
    gain = y_val.pow(2).sum(-1) - (y_val - predicted).pow(2).sum(-1)
    n = gain.shape[0]
    if n < 2:
        return 0.0
    se = float(gain.std()) / math.sqrt(n)
    mean = float(gain.mean())
    return mean / se if se > 0 else (math.inf if mean > 0 else 0.0)


def tuning_split(n: int, fraction: float = 0.2, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Seeded ``(fit, tune)`` indices of the training poses (at least one of each when ``n >= 2``)."""
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed + 7919))
    n_tune = min(max(1, round(fraction * n)), n - 1)
    return perm[n_tune:], perm[:n_tune]


def fit_before_gate(head: ResidualHead, x_train, y_train, *, seed: int = 0) -> ResidualHead:
    """Fit ``head`` on the training pair only, its own tuning on a slice split off it."""
    fit_idx, tune_idx = tuning_split(len(x_train), seed=seed)
    if head.tunes_on_validation:
        return head.fit(x_train[fit_idx], y_train[fit_idx], x_train[tune_idx], y_train[tune_idx])
    return head.fit(x_train, y_train, x_train[tune_idx], y_train[tune_idx])


def select_head(candidates: list[ResidualHead], x_train, y_train, x_val, y_val, *, margin: float = 0.05,
                z_min: float = 2.0, seed: int = 0) -> Selection:
    """Fit each candidate on the training pair, keep the best only if it passes the gate on the validation pair."""
    baseline = rms(y_val)
    scores: dict[str, float] = {}
    best, best_score, best_z = None, float("inf"), 0.0
    for head in candidates:
        fit_before_gate(head, x_train, y_train, seed=seed)
        predicted = head.predict(x_val)
        score = rms(predicted - y_val)
        scores[head.name] = score
        if score < best_score:
            best, best_score, best_z = head, score, paired_gain_z(y_val, predicted)
    n_val = len(y_val)
    if best is not None and best_score < (1.0 - margin) * baseline and best_z > z_min:
        gain = 100.0 * (1.0 - best_score / baseline)
        decision = (f"residual head '{best.name}' kept: validation RMS {best_score:.4f} mm vs {baseline:.4f} mm "
                    f"without it ({gain:.0f} % lower, paired z {best_z:.1f} on {n_val} poses)")
        return Selection(best, scores, baseline, decision)
    tried = ", ".join(f"{k} {v:.4f} mm" for k, v in scores.items())
    why = (f"none beat geometry alone on {n_val} validation poses by {margin * 100:.0f} % with paired z > {z_min:g}"
           f" (best z {best_z:.1f})")
    decision = f"no residual head kept: {why} (geometry {baseline:.4f} mm; {tried})"
    return Selection(None, scores, baseline, decision)


def refit_on_all(head: ResidualHead, x_train, y_train, x_val, y_val, *, seed: int = 0) -> ResidualHead:
    """Refit a kept head on the training and validation poses together, after the gate decided.

    The validation poses have done their job (the decision and its RMS estimate, which stays the
    reported one); holding them out of the final fit only costs data. The tuning slice of the
    training poses still steers the head's own model selection, exactly as in :func:`select_head`.
    """
    fit_idx, tune_idx = tuning_split(len(x_train), seed=seed)
    # A searched hidden layer is the head's model selection: keep it, re-solve only the
    # closed-form output weights on every pose (a new search would be a new, ungated model).
    refitted = head.refit_output(torch.cat([x_train, x_val]), torch.cat([y_train, y_val]))
    if refitted is not None:
        return refitted
    if head.tunes_on_validation:
        x_fit, y_fit = torch.cat([x_train[fit_idx], x_val]), torch.cat([y_train[fit_idx], y_val])
    else:
        x_fit, y_fit = torch.cat([x_train, x_val]), torch.cat([y_train, y_val])
    return head.fit(x_fit, y_fit, x_train[tune_idx], y_train[tune_idx])
