"""Accuracy metrics on 3-D position errors (measured - predicted), and ISO 9283 where it applies.

For each pose the error vector ``e_i`` (instrument frame, mm). :func:`position_metrics` gives the
distribution of ``|e_i|`` over the poses (RMS, mean, std, max, p95, median), per-axis mean and
RMS, and ``mean_error_vector_mm = |mean(e_i)|``, the systematic offset left over all poses (near
zero wherever the instrument frame was fitted to the same poses).

ISO 9283 pose accuracy ``AP`` and repeatability ``RP`` are defined over *repeated visits of one
commanded pose*: ``AP = |mean_j(e_j)|`` (the barycentre of the visits against the command, here
the model's prediction), ``RP = mean_j(l_j) + 3 S_l`` with ``l_j = |e_j - mean(e)|`` and ``S_l``
their sample standard deviation. Over poses that are all different these would mean something
else, so :func:`iso9283_repeated` computes them only for poses whose commanded joints repeat
(within a tolerance) and otherwise says which figures stand in for them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

#: Joint vectors whose largest difference is below this (deg) are visits of the same commanded pose.
REPEAT_TOLERANCE_DEG = 0.01

#: What stands in for ISO 9283 AP/RP when no commanded pose was visited twice.
NO_REPEATS = ("no commanded pose was visited more than once (joint vectors equal within {tol:g} deg), so ISO 9283 "
              "pose accuracy AP and repeatability RP, which are statistics of repeated visits of one pose, cannot be "
              "computed; the figures given instead are the distribution of the 3-D error over distinct poses (RMS, "
              "mean, p95, max) and the mean error vector (the systematic offset over all poses)")


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
    """Metrics of ``(n, 3)`` position errors given in metres; values in mm (see the module docstring)."""
    e = error_m.detach().cpu().to(torch.float64) * 1e3
    dist = e.norm(dim=-1)
    out = {
        "n_poses": int(e.shape[0]),
        **distance_summary(dist, "position"),
        "position_std_mm": float(dist.std()) if e.shape[0] > 1 else 0.0,
        "position_median_mm": float(dist.median()),
        "mean_error_vector_mm": float(e.mean(0).norm()),
    }
    for k, axis in enumerate("xyz"):
        out[f"{axis}_mean_mm"] = float(e[:, k].mean())
        out[f"{axis}_rms_mm"] = float(e[:, k].pow(2).mean().sqrt())
    return out


def repeated_groups(q: torch.Tensor, tolerance_deg: float = REPEAT_TOLERANCE_DEG) -> list[np.ndarray]:
    """Row indices of every commanded pose visited more than once, one array per pose.

    ``q`` ``(n, N)`` rad. Two rows are visits of one pose when no joint differs by more than
    ``tolerance_deg``; visits are chained (connected components), each group sorted.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    joints = np.degrees(q.detach().cpu().numpy().astype(np.float64))
    n = len(joints)
    if n < 2:
        return []
    pairs = np.array(sorted(cKDTree(joints).query_pairs(tolerance_deg, p=np.inf)), dtype=np.int64).reshape(-1, 2)
    if not len(pairs):
        return []
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    counts = np.bincount(label)
    return [np.flatnonzero(label == g) for g in np.flatnonzero(counts > 1)]


def iso9283_repeated(error_m: torch.Tensor, q: torch.Tensor, tolerance_deg: float = REPEAT_TOLERANCE_DEG,
                     rows: Sequence[int] = ()) -> dict:
    """ISO 9283 AP and RP (mm) of every commanded pose the data visits more than once.

    Returns ``repeated_poses`` (how many), ``tolerance_deg`` and, when there are any, ``poses``: one
    entry per repeated pose with the ``index`` of its visits (0-based, into ``q``; ``rows``: their
    rows in the file, when ``rows`` gives each pose's), ``visits``, ``AP_mm`` and ``RP_mm``, plus
    ``AP_max_mm`` / ``RP_max_mm`` over them. Without repeats, ``instead`` says which figures stand
    in for AP and RP and why.
    """
    groups = repeated_groups(q, tolerance_deg)
    out: dict = {"repeated_poses": len(groups), "tolerance_deg": tolerance_deg}
    if not groups:
        out["instead"] = NO_REPEATS.format(tol=tolerance_deg)
        return out
    e = error_m.detach().cpu().to(torch.float64).numpy() * 1e3
    poses = []
    for index in groups:
        visits = e[index]
        centre = visits.mean(0)
        spread = np.linalg.norm(visits - centre, axis=1)
        s = float(spread.std(ddof=1)) if len(index) > 1 else 0.0
        entry = {"index": index.tolist(), "visits": len(index), "AP_mm": float(np.linalg.norm(centre)),
                 "RP_mm": float(spread.mean() + 3 * s)}
        if len(rows):
            entry["rows"] = [int(rows[i]) for i in index]
        poses.append(entry)
    out.update({"visits": int(sum(p["visits"] for p in poses)), "poses": poses,
                "AP_max_mm": max(p["AP_mm"] for p in poses), "RP_max_mm": max(p["RP_mm"] for p in poses)})
    return out
