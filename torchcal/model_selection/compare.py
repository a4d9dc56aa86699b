"""Choosing among candidate models from their cross-validated held-out errors.

Each candidate brings the out-of-fold 3-D error of every pose (mm), from the same folds. The
rule, fixed before any test set is scored:

1. A candidate that adds a learned part (a residual head) is *eligible* only if it beats the
   candidate it is built on (``parent``) by ``min_gain`` in CV RMS **and** its per-pose gain in
   squared error is positive beyond chance: mean over poses more than ``z_min`` standard errors
   above zero, the standard error taken over independent units (configuration groups or time
   blocks, not poses, since near-twins share their errors).
2. Among the eligible candidates, the chosen one is the *simplest* (the order given) whose CV
   mean squared error is within noise of the best: no more than one standard error of the
   paired difference above it, and never less than ``tolerance`` (relative, on RMS) apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Candidate:
    """One model structure and its out-of-fold errors.

    Attributes:
        name: label printed in the table (``geometry``, ``+harmonics``, ``+mlp``, ...).
        errors_mm: ``(n,)`` out-of-fold 3-D error of each pose, mm (or any per-pose error norm).
        parent: the candidate this one adds a learned part to (``None``: a structural option).
        min_gain: relative CV RMS gain over ``parent`` it must show to be eligible.
        detail: free text for the table (hyperparameters, what was fitted).
        head: the residual head this candidate adds to ``parent`` (``None``: no head).
    """

    name: str
    errors_mm: np.ndarray
    parent: str | None = None
    min_gain: float = 0.0
    detail: str = ""
    head: str | None = None

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(np.square(self.errors_mm))))


def paired_difference(a_mm: np.ndarray, b_mm: np.ndarray, units: np.ndarray) -> tuple[float, float]:
    """Mean of ``a^2 - b^2`` over poses (mm^2) and its standard error over ``units``.

    The ratio-estimator standard error of a mean whose poses come in correlated units: per-unit
    sums of the difference, centred on the unit's share of the mean.
    """
    d = np.square(a_mm) - np.square(b_mm)
    n = len(d)
    ids, inverse = np.unique(units, return_inverse=True)
    u = len(ids)
    if u < 2:
        return float(d.mean()), math.inf
    totals = np.bincount(inverse, weights=d, minlength=u)
    counts = np.bincount(inverse, minlength=u)
    mean = float(d.sum() / n)
    se = float(np.sqrt(u / (u - 1) * np.sum(np.square(totals - counts * mean))) / n)
    return mean, se


@dataclass
class Comparison:
    """The outcome: every candidate's CV RMS, the chosen one, and why."""

    protocol: str
    rows: list[dict] = field(default_factory=list)
    chosen: str = ""
    reason: str = ""
    #: out-of-fold 3-D errors (mm) of every candidate, by name (not serialised)
    errors_mm: dict[str, np.ndarray] = field(default_factory=dict, repr=False, compare=False)
    #: the residual head of each row that adds one, by row name (not serialised)
    heads: dict[str, str] = field(default_factory=dict, repr=False, compare=False)

    @property
    def chosen_head(self) -> str | None:
        """The residual head of the chosen row (``None``: the chosen row adds none)."""
        return self.heads.get(self.chosen)

    def to_dict(self) -> dict:
        return {"protocol": self.protocol, "chosen": self.chosen, "reason": self.reason, "candidates": self.rows}

    def format_table(self) -> str:
        """A plain-text table (fixed width) for the console and the report."""
        width = max([len("candidate")] + [len(row["name"]) for row in self.rows])
        lines = [f"model selection: {self.protocol}",
                 f"  {'candidate':<{width}} {'CV RMS mm':>10} {'vs best':>9} {'1 SE':>8}  verdict"]
        for row in self.rows:
            mark = "chosen" if row["name"] == self.chosen else row["verdict"]
            if math.isfinite(row["cv_rms_mm"]):
                numbers = f"{row['cv_rms_mm']:>10.4f} {row['vs_best_pct']:>+8.1f}% {row['se_pct']:>7.1f}%"
            else:
                numbers = f"{'-':>10} {'-':>9} {'-':>8}"
            lines.append(f"  {row['name']:<{width}} {numbers}  {mark}")
        lines.append(f"  -> {self.chosen}: {self.reason}")
        return "\n".join(lines)


def compare_candidates(candidates: list[Candidate], units: np.ndarray, protocol: str, *, tolerance: float = 0.01,
                       z_min: float = 2.0, excluded: dict[str, str] | None = None) -> Comparison:
    """Apply the module's rule to ``candidates`` (simplest first); ``units`` ``(n,)`` label independent units.

    ``excluded``: candidates ruled out by a later check (name -> why); they are scored and listed
    but are neither the reference ("vs best") nor chosen, so that every verdict is relative to
    the candidate the decision was taken against. Each verdict names that reference.
    """
    if not candidates:
        raise ValueError("no candidates to compare")
    by_name = {c.name: c for c in candidates}
    eligible: dict[str, str] = {}
    for cand in candidates:
        if excluded and cand.name in excluded:
            eligible[cand.name] = excluded[cand.name]
            continue
        if cand.parent is None:
            eligible[cand.name] = "eligible"
            continue
        parent = by_name[cand.parent]
        gain = 1.0 - cand.rms / parent.rms if parent.rms > 0 else 0.0
        mean, se = paired_difference(parent.errors_mm, cand.errors_mm, units)
        z = mean / se if se > 0 else (math.inf if mean > 0 else 0.0)
        if gain >= cand.min_gain and z > z_min:
            eligible[cand.name] = "eligible"
        else:
            eligible[cand.name] = (f"rejected: {100 * gain:+.1f} % vs {cand.parent} (needs {100 * cand.min_gain:.0f} %), "
                                   f"paired z {z:.1f} (needs > {z_min:g})")
    pool = [c for c in candidates if eligible[c.name] == "eligible"]
    best = min(pool, key=lambda c: c.rms)
    floor = ((1.0 + tolerance) ** 2 - 1.0) * best.rms**2
    comparison = Comparison(protocol, errors_mm={c.name: c.errors_mm for c in candidates},
                            heads={c.name: c.head for c in candidates if c.head is not None})
    chosen = None
    for cand in candidates:
        mean, se = paired_difference(cand.errors_mm, best.errors_mm, units)
        within = eligible[cand.name] == "eligible" and mean <= max(se, floor)
        if within and chosen is None:
            chosen = cand
        verdict = eligible[cand.name] if eligible[cand.name] != "eligible" else (
            "best" if cand is best else f"within noise of {best.name}" if within else f"worse than {best.name} beyond noise")
        comparison.rows.append({
            "name": cand.name, "cv_rms_mm": cand.rms, "vs_best_pct": 100.0 * (cand.rms / best.rms - 1.0),
            "se_pct": 100.0 * se / (2 * best.rms**2) if math.isfinite(se) else math.inf,
            "verdict": verdict, "detail": cand.detail,
        })
    assert chosen is not None  # the best itself is always within noise of itself
    comparison.chosen = chosen.name
    if chosen is best:
        lower = [c.name for c in candidates if c.rms < best.rms and c not in pool]  # lower, but not eligible
        comparison.reason = f"lowest CV RMS ({best.rms:.4f} mm)" + (" among the eligible candidates" if lower else "")
    else:
        comparison.reason = (f"simplest within noise of the best ({best.name} {best.rms:.4f} mm; "
                             f"{chosen.rms:.4f} mm here, difference below one standard error or {100 * tolerance:g} %)")
    return comparison
