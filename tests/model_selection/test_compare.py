"""The selection rule: simplest within noise of the best; learned parts need gain beyond chance."""

from __future__ import annotations

import numpy as np
import pytest

from torchcal.model_selection.compare import Candidate, compare_candidates, paired_difference


def test_paired_difference_matches_the_textbook_standard_error_for_independent_poses():
    rng = np.random.default_rng(0)
    a, b = rng.rayleigh(1.0, 400), rng.rayleigh(1.0, 400)
    mean, se = paired_difference(a, b, np.arange(400))
    d = a**2 - b**2
    assert mean == pytest.approx(d.mean())
    assert se == pytest.approx(d.std(ddof=1) / np.sqrt(400), rel=1e-12)


def test_correlated_units_widen_the_standard_error():
    rng = np.random.default_rng(1)
    groups = np.repeat(np.arange(20), 20)
    shared = rng.normal(0, 1, 20)[groups]  # a group's poses share their difference
    a = np.sqrt(np.clip(1.0 + shared + 0.05 * rng.normal(size=400), 0, None))
    b = np.ones(400)
    _, se_poses = paired_difference(a, b, np.arange(400))
    _, se_groups = paired_difference(a, b, groups)
    assert se_groups > 3 * se_poses


def test_simplest_within_noise_is_kept():
    rng = np.random.default_rng(2)
    base = rng.rayleigh(0.3, 500)
    units = np.arange(500)
    tiny_better = base * 0.995
    out = compare_candidates([Candidate("geometry", base), Candidate("geometry+harmonics", tiny_better)], units, "test")
    assert out.chosen == "geometry"
    clearly_better = base * 0.8
    out = compare_candidates([Candidate("geometry", base), Candidate("geometry+harmonics", clearly_better)], units, "test")
    assert out.chosen == "geometry+harmonics"
    assert "lowest CV RMS" in out.reason


def test_a_head_needs_margin_and_evidence():
    rng = np.random.default_rng(3)
    parent = rng.rayleigh(0.3, 300)
    units = np.repeat(np.arange(30), 10)
    noisy = parent * np.exp(rng.normal(-0.03, 0.3, 300))  # ~3 % better on average, huge scatter
    out = compare_candidates([Candidate("geometry", parent), Candidate("geometry+mlp", noisy, parent="geometry", min_gain=0.05)],
                             units, "test")
    assert out.chosen == "geometry"
    assert out.rows[1]["verdict"].startswith("rejected")
    good = parent * 0.6
    out = compare_candidates([Candidate("geometry", parent), Candidate("geometry+mlp", good, parent="geometry", min_gain=0.05)],
                             units, "test")
    assert out.chosen == "geometry+mlp"
    assert "geometry+mlp" in out.format_table()


def test_verdicts_name_their_reference_and_a_later_rejection_restates_them():
    """A head that wins the CV but is ruled out by a later check (time blocks) is not the reference of
    the structures' verdicts: they are restated against the best structure, as the decision is."""
    rng = np.random.default_rng(4)
    units = np.repeat(np.arange(50), 10)
    geometry = rng.rayleigh(0.3, 500)
    wrist = geometry * 0.999  # within noise of geometry
    head = geometry * 0.6  # clearly better than both
    cands = [Candidate("geometry", geometry), Candidate("geometry+wrist", wrist),
             Candidate("geometry+mlp", head, parent="geometry", min_gain=0.05)]
    out = compare_candidates(cands, units, "test")
    assert out.chosen == "geometry+mlp"
    verdicts = {r["name"]: r["verdict"] for r in out.rows}
    assert verdicts["geometry"] == "worse than geometry+mlp beyond noise" and verdicts["geometry+mlp"] == "best"
    later = compare_candidates(cands, units, "test", excluded={"geometry+mlp": "rejected: not on time blocks"})
    assert later.chosen == "geometry"
    verdicts = {r["name"]: r["verdict"] for r in later.rows}
    assert verdicts == {"geometry": "within noise of geometry+wrist", "geometry+wrist": "best",
                        "geometry+mlp": "rejected: not on time blocks"}
    rows = {r["name"]: r for r in later.rows}
    assert rows["geometry+wrist"]["vs_best_pct"] == 0.0 and rows["geometry+mlp"]["vs_best_pct"] < -30
