"""Position metrics, and ISO 9283 AP/RP only where a commanded pose was visited more than once."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcal.core.metrics import iso9283_repeated, position_metrics, repeated_groups


def test_position_metrics_over_distinct_poses_claim_no_iso_figures():
    e = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, -2.0]], dtype=torch.float64) * 1e-3
    m = position_metrics(e)
    assert m["position_rms_mm"] == pytest.approx(math.sqrt(3.0))
    assert m["mean_error_vector_mm"] == pytest.approx(float(torch.tensor([1.0, 2.0, -2.0]).norm() / 3))
    assert not any("iso" in k or "AP" in k for k in m)


def test_repeated_visits_are_grouped_within_the_tolerance():
    q = torch.tensor(np.radians([[0, 0, 0], [10, 0, 0], [0.004, 0, 0.003], [10, 0.02, 0], [0.0, 0, -0.004]]))
    groups = repeated_groups(q, tolerance_deg=0.01)
    assert [g.tolist() for g in groups] == [[0, 2, 4]]  # row 3 differs by 0.02 deg: another pose


def test_iso9283_ap_and_rp_of_the_repeated_pose():
    q = torch.tensor(np.radians([[0, 0, 0]] * 4 + [[5, 5, 5]]))
    q[1, 0] += math.radians(0.001)  # a repeat within the tolerance
    visits = np.array([[1.0, 0, 0], [1.2, 0, 0], [0.8, 0, 0], [1.0, 0.3, 0]])
    e = torch.tensor(np.vstack([visits, [[9.0, 9, 9]]]) * 1e-3)
    iso = iso9283_repeated(e, q, rows=[2, 3, 5, 6, 7])
    assert iso["repeated_poses"] == 1 and iso["visits"] == 4
    pose = iso["poses"][0]
    centre = visits.mean(0)
    spread = np.linalg.norm(visits - centre, axis=1)
    assert pose["AP_mm"] == pytest.approx(np.linalg.norm(centre))
    assert pose["RP_mm"] == pytest.approx(spread.mean() + 3 * spread.std(ddof=1))
    assert pose["rows"] == [2, 3, 5, 6] and pose["index"] == [0, 1, 2, 3]


def test_without_repeats_iso9283_says_what_stands_in():
    q = torch.rand(30, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    iso = iso9283_repeated(torch.zeros(30, 3, dtype=torch.float64), q)
    assert iso["repeated_poses"] == 0 and "poses" not in iso
    assert "cannot be computed" in iso["instead"] and "RMS" in iso["instead"]
