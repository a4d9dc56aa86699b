"""The CLI on public real-robot measurements, read in place (skipped when the folder is absent)."""

from __future__ import annotations

import json

import pytest

from tests.conftest import REAL_DATA
from torchcal.cli import main

pytestmark = pytest.mark.real


def _fit_and_score(tmp_path, dataset, fit_file, test_file, *extra_eval):
    folder = REAL_DATA / dataset
    model = tmp_path / "model"
    assert main(["fit", "--robot", str(folder / "robot.yaml"), "--data", str(folder / fit_file), "--out", str(model), "residual=none"]) == 0
    out = tmp_path / "m.json"
    assert main(["evaluate", "--model", str(model), "--data", str(folder / test_file), "--json", str(out), *extra_eval]) == 0
    return json.loads(out.read_text())


@pytest.mark.slow
def test_ur5_source_split(tmp_path):
    """UR5 (three parallel axes, Hayati beta), 1000 grid poses -> 20 test poses of the source."""
    metrics = _fit_and_score(tmp_path, "jacobi-ur5-gts3800", "poses.csv", "poses_test.csv")
    assert metrics["n_poses"] == 20
    # published: 2.5664 mm before, 0.1549 mm after (hybrid model); geometry alone reaches ~0.10
    assert metrics["position_mean_mm"] < 0.11


@pytest.mark.slow
def test_ur10_fit_on_series_c_score_on_series_b_after_registration(tmp_path):
    """Series B and C were measured in different tracker frames: --register re-fits only the frame.

    B's 6-D file (the same rows with the T-Mac's orientation) also scores the orientation that the
    position-only fit of C claims for the flange."""
    metrics = _fit_and_score(tmp_path, "ipa-ur10-tmac", "poses_C_random.csv", "poses_B_joint_6d.csv", "--register")
    assert metrics["n_poses"] > 1000
    # geometry alone 0.904 mm; first harmonics fitted over C's short joint arcs 1.40 mm; the default's
    # structure (gravity compliance; harmonics only on joints that turned half a revolution) 0.532 mm
    assert metrics["position_rms_mm"] < 0.60
    leakage = metrics["leakage"]
    assert leakage["twin_share"] < 0.01 and "repeat a training configuration" not in leakage["warning"]  # the home pose
    # B's joint sweeps lie further from C's random poses than a grouped CV of C holds any out: said so
    assert leakage["far_share"] > 0.5 and "extrapolates" in leakage["warning"]
    # orientation never measured in the fit: 0.0597 deg RMS against the nominal robot's 0.0852 deg
    orientation = metrics["orientation"]
    assert orientation["orientation_rms_deg"] < 0.8 * orientation["nominal"]["orientation_rms_deg"]


@pytest.mark.slow
def test_ur10_fit_on_grid_series_a_transfers_to_series_c(tmp_path):
    """3000 rows of the wrist-swept grid A (numpy default_rng(0)), scored on all of C re-registered."""
    import numpy as np

    lines = (REAL_DATA / "ipa-ur10-tmac" / "poses_A_grid.csv").read_text().splitlines()
    rows = np.sort(np.random.default_rng(0).permutation(len(lines) - 1)[:3000]) + 1
    subset = tmp_path / "A3000.csv"
    subset.write_text("\n".join([lines[0]] + [lines[i] for i in rows]) + "\n")
    model, out = tmp_path / "model", tmp_path / "m.json"
    folder = REAL_DATA / "ipa-ur10-tmac"
    assert main(["fit", "--robot", str(folder / "robot.yaml"), "--data", str(subset), "--out", str(model), "residual=none",
                 "progress=false"]) == 0
    assert main(["evaluate", "--model", str(model), "--data", str(folder / "poses_C_random.csv"), "--json", str(out),
                 "--register"]) == 0
    metrics = json.loads(out.read_text())
    assert metrics["position_rms_mm"] < 0.59  # geometry alone 0.575 mm


def test_wam_gravity_compliance_lowers_the_held_out_error(tmp_path):
    """Cable-driven WAM: joint sag under its own weight, identified with the geometry on the grid poses."""
    folder = REAL_DATA / "jacobi-wam-gts3800"
    scores = {}
    for option in ("none", "wrist"):
        model = tmp_path / option
        assert main(["fit", "--robot", str(folder / "robot.yaml"), "--data", str(folder / "poses_7dof.csv"),
                     "--out", str(model), "residual=none", f"gravity_compliance={option}", "progress=false"]) == 0
        out = tmp_path / f"{option}.json"
        assert main(["evaluate", "--model", str(model), "--data", str(folder / "poses_7dof_test.csv"), "--json", str(out)]) == 0
        scores[option] = json.loads(out.read_text())["position_mean_mm"]
    assert scores["wrist"] < 0.97 * scores["none"]
