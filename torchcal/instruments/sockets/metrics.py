"""Scores of a robot model on socket data (no instrument: the data score themselves).

* **Consistency**: distance of each configuration's predicted ball centre from its group's
  point, that point fitted on the scored rows themselves (the group mean: a new placement is a
  new unknown point). Reported as mean, RMS and max over configurations, mm.
* **Distortion**: per placement with two sockets, ``| |c_a - c_b| - D |`` of the two group
  means against the fixture's distance ``D``; mean and max over placements, mm.
"""

from __future__ import annotations

import torch

from torchcal.instruments.sockets.data import SocketData
from torchcal.instruments.sockets.model import group_means


def socket_metrics(ball_centres: torch.Tensor, data: SocketData, distance_mm: float = 50.0) -> dict:
    """Consistency and distortion of predicted ball centres ``(n, 3)`` (any fixed frame, m)."""
    centres = group_means(ball_centres, data.group.to(ball_centres.device), len(data.groups))
    dist = (ball_centres - centres[data.group]).norm(dim=-1) * 1e3
    distortion = []
    per_placement = {}
    for name, a, b in data.pairs():
        error = abs(float((centres[a] - centres[b]).norm()) * 1e3 - distance_mm)
        distortion.append(error)
        per_placement[name] = {"distortion_mm": error}
    for name in data.placements:
        rows = torch.tensor([p == name for p in data.placement], device=dist.device)
        per_placement.setdefault(name, {})["consistency_mean_mm"] = float(dist[rows].mean())
    return {
        "n_rows": len(data),
        "n_groups": len(data.groups),
        "n_placements": len(data.placements),
        "consistency_mean_mm": float(dist.mean()),
        "consistency_rms_mm": float(dist.square().mean().sqrt()),
        "consistency_max_mm": float(dist.max()),
        "distortion_mean_mm": sum(distortion) / len(distortion) if distortion else float("nan"),
        "distortion_max_mm": max(distortion) if distortion else float("nan"),
        "per_placement": per_placement,
    }
