"""The prior on the public UR5 set: the tool given as the user knows it, geometry only (issue case)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from tests.conftest import REAL_DATA
from torchcal.cli import main

pytestmark = pytest.mark.real


def test_ur5_with_its_tool_keeps_unseen_directions_at_the_prior(tmp_path):
    folder = REAL_DATA / "jacobi-ur5-gts3800"
    if not folder.is_dir():
        pytest.skip("real data folder absent")
    model = tmp_path / "model"
    assert main(["fit", "--robot", str(folder / "robot.yaml"), "--data", str(folder / "poses.csv"), "--out", str(model),
                 "tool_mm=[0.133,0.183,33.724]", "residual=none", "gravity_compliance=none", "joint_harmonics=none",
                 "progress=false"]) == 0
    meta = json.loads((model / "calibration.json").read_text())
    rows = {r["name"]: r for r in meta["prior"]["parameters"]}
    # every parameter beyond its tolerance is named in a warning
    warned = " ".join(n for n in meta["notes"] if "beyond their manufacturing tolerance" in n)
    for name, r in rows.items():
        if r["beyond_tolerance"]:
            assert f"{name} " in warned, name
    # what position data cannot see stays at the prior (the rank cut fitted theta5 -8.9 deg, alpha6 -7.6 deg)
    for name in ("theta5", "alpha6", "theta6", "d6"):
        assert abs(rows[name]["moved_sigmas"]) < 1.0 and rows[name]["sigma_ratio"] > 0.9, rows[name]
    out = tmp_path / "m.json"
    assert main(["evaluate", "--model", str(model), "--data", str(folder / "poses_test.csv"), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["position_rms_mm"] <= 0.105  # the rank cut: 0.1042 mm
    # the flange-TCP compensator: joint corrections of a fraction of a degree, not the rank cut's 3.5 deg
    from torchcal.compensate.compensator import CompensatorGraph
    from torchcal.compensate.production_tcp import production_view, tcp_transform
    from torchcal.data.measurements import load_measurements
    from torchcal.stages.store import load_model

    stored = load_model(model)
    data = load_measurements(folder / "poses_test.csv", stored.robot)
    graph = CompensatorGraph.from_stored(production_view(stored, tcp_transform(None, None)))
    with torch.no_grad():
        q_c, _ = graph.solve(data.q)
    assert math.degrees(float((q_c - data.q).abs().max())) < 1.0
