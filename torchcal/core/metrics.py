"""Accuracy metrics in ISO 9283 terms, on 3-D position errors (measured - predicted).

For each pose the error vector ``e_i`` (instrument frame, mm). Reported: the distribution of
``|e_i|`` (RMS, mean, std, max, p95, median), per-axis mean and RMS, and the ISO 9283
pose-accuracy style ``AP_p = |mean(e_i)|`` (offset of the barycentre) with its per-axis parts,
plus ``AP + 3 S`` where ``S`` is the standard deviation of ``|e_i - mean(e)|`` (the spread).
"""

from __future__ import annotations

import torch


def position_metrics(error_m: torch.Tensor) -> dict[str, float]:
    """Metrics of ``(n, 3)`` position errors given in metres; values in mm."""
    e = error_m.detach().cpu().to(torch.float64) * 1e3
    dist = e.norm(dim=-1)
    mean_vec = e.mean(0)
    spread = (e - mean_vec).norm(dim=-1)
    out = {
        "n_poses": int(e.shape[0]),
        "position_rms_mm": float(dist.pow(2).mean().sqrt()),
        "position_mean_mm": float(dist.mean()),
        "position_std_mm": float(dist.std()) if e.shape[0] > 1 else 0.0,
        "position_median_mm": float(dist.median()),
        "position_max_mm": float(dist.max()),
        "position_p95_mm": float(torch.quantile(dist, 0.95)),
        "iso9283_AP_mm": float(mean_vec.norm()),
        "iso9283_AP_plus_3S_mm": float(mean_vec.norm() + 3 * (spread.pow(2).sum() / max(1, e.shape[0] - 1)).sqrt()),
    }
    for k, axis in enumerate("xyz"):
        out[f"{axis}_mean_mm"] = float(e[:, k].mean())
        out[f"{axis}_rms_mm"] = float(e[:, k].pow(2).mean().sqrt())
    return out
