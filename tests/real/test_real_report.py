"""Reports and the nominal baseline on public real-robot measurements (skipped when the folder is absent)."""

from __future__ import annotations

import re

import pytest

from tests.conftest import REAL_DATA
from torchcal.cli import main
from torchcal.core.metrics import position_metrics
from torchcal.data.measurements import load_measurements
from torchcal.kinematics.robot import load_robot
from torchcal.stages.geometry import nominal_errors, registered_errors

pytestmark = pytest.mark.real


def test_irb120_nominal_baseline_fits_frame_and_tool():
    """IRB 120 (982 poses, SMR 1): a frame-only 'before' overstates the gain; the tool sits 5.6 mm off its guess."""
    folder = REAL_DATA / "icelinker-irb120-faro"
    robot = load_robot(folder / "robot.yaml")
    data = load_measurements(folder / "poses.csv", robot)
    frame_only = position_metrics(registered_errors(robot.tcp_position(data.q), data.position))["position_rms_mm"]
    with_tool = position_metrics(nominal_errors(robot, data))["position_rms_mm"]
    assert frame_only == pytest.approx(1.130, abs=0.002)
    assert with_tool == pytest.approx(0.870, abs=0.002)


def test_fit_on_a_small_real_set_writes_its_report(tmp_path):
    """Rokae 380 (30 poses): fit with the defaults; both reports, the tables, the figures inline."""
    folder = REAL_DATA / "lmpytorch-rokae380-30"
    model = tmp_path / "model"
    assert main(["fit", "--robot", str(folder / "robot.yaml"), "--data", str(folder / "poses.csv"), "--out", str(model),
                 "progress=false"]) == 0
    md, page = (model / "report.md").read_text(), (model / "report.html").read_text()
    tables = set(re.findall(r'data-table="([^"]+)"', page))
    assert {"accuracy", "model_selection", "per_axis", "worst_poses_1", "frames", "parameters", "compensator"} <= tables
    linked = re.findall(r"\]\((figures/[^)]+\.png)\)", md)
    assert len(linked) == len(re.findall(r'src="data:image/png;base64,', page)) >= 6
    assert "training poses of poses.csv, optimistic" in md and "held out: out-of-fold" in md
