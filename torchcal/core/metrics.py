"""Accuracy metrics in ISO 9283 terms, on 3-D position errors (measured - predicted).

For each pose the error vector ``e_i`` (instrument frame, mm). Reported: the distribution of
``|e_i|`` (RMS, mean, std, max, p95, median), per-axis mean and RMS, and the ISO 9283
pose-accuracy style ``AP_p = |mean(e_i)|`` (offset of the barycentre) with its per-axis parts,
plus ``AP + 3 S`` where ``S`` is the standard deviation of ``|e_i - mean(e)|`` (the spread).
"""

from __future__ import annotations

import torch


def distance_summary(values_mm: torch.Tensor, prefix: str, *, mean_key: str = "mean") -> dict[str, float]:
    """RMS, mean, max and 95th percentile of non-negative distances ``(n,)`` given in mm.

    Keys ``{prefix}_rms_mm``, ``{prefix}_{mean_key}_mm``, ``{prefix}_max_mm``, ``{prefix}_p95_mm``;
    every per-kind metric (positions, lengths, deflections, point-to-plane distances) uses it.
    """
    d = values_mm.detach().cpu().to(torch.float64)
    return {
        f"{prefix}_rms_mm": float(d.pow(2).mean().sqrt()),
        f"{prefix}_{mean_key}_mm": float(d.mean()),
        f"{prefix}_max_mm": float(d.max()),
        f"{prefix}_p95_mm": float(torch.quantile(d, 0.95)),
    }


def position_metrics(error_m: torch.Tensor) -> dict[str, float]:
    """Metrics of ``(n, 3)`` position errors given in metres; values in mm."""
    e = error_m.detach().cpu().to(torch.float64) * 1e3
    dist = e.norm(dim=-1)
    mean_vec = e.mean(0)
    spread = (e - mean_vec).norm(dim=-1)
    out = {
        "n_poses": int(e.shape[0]),
        **distance_summary(dist, "position"),
        "position_std_mm": float(dist.std()) if e.shape[0] > 1 else 0.0,
        "position_median_mm": float(dist.median()),
        "iso9283_AP_mm": float(mean_vec.norm()),
        "iso9283_AP_plus_3S_mm": float(mean_vec.norm() + 3 * (spread.pow(2).sum() / max(1, e.shape[0] - 1)).sqrt()),
    }
    for k, axis in enumerate("xyz"):
        out[f"{axis}_mean_mm"] = float(e[:, k].mean())
        out[f"{axis}_rms_mm"] = float(e[:, k].pow(2).mean().sqrt())
    return out
