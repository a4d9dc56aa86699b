"""First-harmonic joint errors on the WAM, read in place (skipped when ../shared/data/real is absent)."""

from __future__ import annotations

import json

import pytest

from tests.conftest import REAL_DATA
from torchcal.cli import main

pytestmark = pytest.mark.real

WAM_PUBLISHED_MEAN_MM = 2.9178  # hybrid model of the source, on its 20 test poses


def test_wam_cv_chooses_harmonics_and_beats_the_published_mean(tmp_path):
    """Chosen by grouped 5-fold CV on the 216 grid poses only; scored on the 20 test poses in the base frame."""
    folder = REAL_DATA / "jacobi-wam-gts3800"
    model = tmp_path / "model"
    assert main(["fit", "--robot", str(folder / "robot.yaml"), "--data", str(folder / "poses_7dof.csv"), "--out", str(model),
                 "residual=none", "gravity_compliance=auto", "joint_harmonics=auto", "progress=false"]) == 0
    meta = json.loads((model / "calibration.json").read_text())
    assert any(n.startswith("structure chosen by 5-fold CV") and "harmonics" in n.rsplit("->", 1)[1]
               for n in meta["notes"])
    coefficients = meta["joint_harmonics"]["coefficients_rad"]
    assert all(row[-1] == 0.0 for row in coefficients)  # the last joint gets none
    out = tmp_path / "m.json"
    assert main(["evaluate", "--model", str(model), "--data", str(folder / "poses_7dof_test.csv"), "--json", str(out)]) == 0
    metrics = json.loads(out.read_text())
    assert metrics["n_poses"] == 20
    assert metrics["position_mean_mm"] < WAM_PUBLISHED_MEAN_MM
