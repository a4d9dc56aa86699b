"""A robot with a continuous joint (no limits) through simulate, fit, evaluate, export, compensate and motion.

The truth is the physics: a continuous joint a whole turn further puts the arm where it was, so
files with some of its angles wrapped by whole turns must give the same calibration figures, the
same joint corrections and no clipping anywhere (the ONNX compensator is run with onnxruntime).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torchcal.cli import main
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import load_robot
from torchcal.motion.waypoints import waypoints_csv

pytestmark = pytest.mark.slow

FIXTURES = Path(__file__).parent / "kinematics" / "fixtures"
CONTINUOUS = FIXTURES / "arm6_continuous.urdf"
LIMITED = FIXTURES / "arm6_offset.urdf"  # the same arm with joint 6 limited to +-3 rad


def _wrap(src: Path, dst: Path, turns: tuple[int, ...]) -> Path:
    """``src`` with q6 moved by whole turns (deg), row k by ``turns[k % len(turns)]``."""
    rows = list(csv.reader(src.read_text().splitlines()))
    j = rows[0].index("q6")
    for k, row in enumerate(rows[1:]):
        row[j] = repr(float(row[j]) + 360.0 * turns[k % len(turns)])
    with dst.open("w", newline="") as handle:
        csv.writer(handle).writerows(rows)
    return dst


def _rms(tmp_path: Path, model: Path, data: Path) -> float:
    out = tmp_path / f"{data.stem}.json"
    assert main(["evaluate", "--model", str(model), "--data", str(data), "--json", str(out)]) == 0
    return json.loads(out.read_text())["position_rms_mm"]


def test_continuous_joint_end_to_end(tmp_path, capsys):
    case, model, export = tmp_path / "case", tmp_path / "model", tmp_path / "export"
    assert main(["simulate", "--out", str(case), f"robot={CONTINUOUS}", "n_train=120", "n_test=60", "seed=3"]) == 0
    train = _wrap(case / "train.csv", tmp_path / "train.csv", (0, 1, -2))
    test = _wrap(case / "test.csv", tmp_path / "test.csv", (0, -1, 3))
    assert max(abs(float(r["q6"])) for r in csv.DictReader(train.open())) > 360  # beyond any +-180 deg
    # the same arm with limits refuses the wrapped file; the continuous one fits it
    assert main(["fit", "--robot", str(LIMITED), "--data", str(train), "--out", str(tmp_path / "refused"), "residual=none"]) == 2
    assert "outside joint 6's limits" in capsys.readouterr().err
    assert main(["fit", "--robot", str(CONTINUOUS), "--data", str(train), "--out", str(model)]) == 0
    capsys.readouterr()
    wrapped, plain = _rms(tmp_path, model, test), _rms(tmp_path, model, case / "test.csv")
    assert wrapped == pytest.approx(plain, rel=1e-9) and wrapped < 0.1  # mm: calibrated to the twin's noise

    assert main(["export", "--model", str(model), "--out", str(export)]) == 0
    text = (export / "manifest.json").read_text()
    manifest = json.loads(text)
    assert "Infinity" not in text and "NaN" not in text
    assert manifest["joint_limits_rad"][5] is None and manifest["joint_limits_rad"][0] == pytest.approx([-3.0, 3.0])
    assert manifest["continuous_joints"] == ["j6"]
    from torchcal.compensate.runtime import CompensatorRuntime  # onnxruntime runs the graph

    runtime = CompensatorRuntime(export, precision="float64", threads=1)
    base = np.array([0.3, -0.5, 0.8, 0.4, 0.7, 0.0])
    q = np.tile(base, (5, 1))
    q[:, 5] = [0.2, 3.1, 3.3, 0.2 + 2 * math.pi, 0.2 - 6 * math.pi]  # 3.3 rad and beyond: outside +-pi
    correction = runtime.correct(q) - q
    # never clipped to a turn: the corrections of one pose a whole turn apart agree, and stay small
    np.testing.assert_allclose(correction[3], correction[0], atol=1e-9)
    np.testing.assert_allclose(correction[4], correction[0], atol=1e-9)
    assert np.abs(correction).max() < math.radians(5)

    program = tmp_path / "program.csv"
    program.write_text("q1,q2,q3,q4,q5,q6\n10,-20,30,40,50,40\n10,-20,30,40,50,400\n10,-20,30,40,50,-680\n")
    out = tmp_path / "corrected.csv"
    assert main(["compensate", "--model", str(model), "--targets", str(program), "--out", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    moved = [float(r["q6"]) - q6 for r, q6 in zip(rows, (40.0, 400.0, -680.0))]
    assert moved[1] == pytest.approx(moved[0], abs=1e-6) and moved[2] == pytest.approx(moved[0], abs=1e-6)


def test_motion_turns_a_continuous_joint_past_half_a_turn(tmp_path, capsys):
    """From q6 = 160 deg to the pose at 220 deg: the continuous arm turns on; the limited one is refused."""
    robot = load_robot(CONTINUOUS)
    model = ErrorModel(robot)
    start = torch.tensor([10.0, -20.0, 30.0, 40.0, 50.0, 160.0], dtype=torch.float64)
    end = start.clone()
    end[5] = 220.0
    poses = torch.stack([model.tcp_pose(torch.deg2rad(v), model.nominal_vector()) for v in (start, end)])
    path = tmp_path / "path.csv"
    path.write_text(waypoints_csv(poses))
    start_arg = "start=[" + ",".join(f"{v:g}" for v in start.tolist()) + "]"
    out = tmp_path / "traj.csv"
    assert main(["motion", "--robot", str(CONTINUOUS), "--path", str(path), "--out", str(out), start_arg]) == 0
    last = [float(v) for v in out.read_text().splitlines()[-1].split(",")]
    assert last[6] == pytest.approx(220.0, abs=1e-3)
    assert main(["motion", "--robot", str(LIMITED), "--path", str(path), "--out", str(tmp_path / "t2.csv"), start_arg]) == 2
    assert "outside its range" in capsys.readouterr().err
