"""The profile path of the command line: simulate -> fit -> sensor.json against truth.json -> evaluate."""

from __future__ import annotations

import json
import math

import numpy as np

from torchcal.cli import main


def _angle_deg(a, b) -> float:
    c = (np.trace(np.asarray(a).T @ np.asarray(b)) - 1) / 2
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def test_simulate_fit_evaluate_profile(tmp_path, capsys):
    case, out = tmp_path / "case", tmp_path / "sensor"
    assert main(["simulate", "instrument=profile", "--out", str(case), "seed=7"]) == 0
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "profile.csv"), "--out", str(out)]) == 0
    truth = json.loads((case / "truth.json").read_text())
    sensor = json.loads((out / "sensor.json").read_text())
    assert _angle_deg(sensor["R_flange_sensor"], truth["R_flange_sensor"]) < 0.01
    assert np.linalg.norm(np.subtract(sensor["t_flange_sensor_mm"], truth["t_flange_sensor_mm"])) < 0.02
    assert sensor["start"] == "closed_form" and _angle_deg(sensor["closed_form"]["R_flange_sensor"], truth["R_flange_sensor"]) < 0.05
    assert len(sensor["sigma_rotation_deg"]) == 3 and max(sensor["sigma_t_mm"]) < 0.01
    metrics_path = tmp_path / "m.json"
    assert main(["evaluate", "--model", str(out), "--data", str(case / "profile.csv"), "--json", str(metrics_path)]) == 0
    metrics = json.loads(metrics_path.read_text())
    assert math.isclose(metrics["point_plane_rms_mm"], sensor["fit"]["point_plane"]["rms_mm"], rel_tol=1e-3)
    assert metrics["point_plane_rms_mm"] < 0.015


def test_units_override_and_bad_files(tmp_path, capsys):
    case = tmp_path / "case"
    main(["simulate", "instrument=profile", "--out", str(case), "seed=8", "points_per_scan=60"])
    lines = (case / "profile.csv").read_text().splitlines()
    rows = [l.split(",") for l in lines[1:]]
    converted = [lines[0]] + [
        ",".join([r[0]] + [f"{math.radians(float(v)):.15g}" for v in r[1:7]] + [f"{float(v) * 1e-3:.12g}" for v in r[7:9]] + [r[9]])
        for r in rows
    ]
    (tmp_path / "si.csv").write_text("\n".join(converted) + "\n")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "profile.csv"), "--out", str(a)]) == 0
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(tmp_path / "si.csv"), "--out", str(b),
                 "joint_unit=rad", "length_unit=m"]) == 0
    ra, rb = (json.loads((p / "sensor.json").read_text()) for p in (a, b))
    assert np.abs(np.subtract(ra["R_flange_sensor"], rb["R_flange_sensor"])).max() < 1e-9
    assert np.allclose(ra["t_flange_sensor_mm"], rb["t_flange_sensor_mm"], atol=1e-6)
    # two placements only: a degenerate motion set is one clear line on stderr, exit status 2
    (tmp_path / "two.csv").write_text("\n".join([lines[0]] + [l for l, r in zip(lines[1:], rows) if r[9] != "2"]) + "\n")
    capsys.readouterr()
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(tmp_path / "two.csv"), "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "fewer than 3 plane orientations" in err and "two.csv" in err and len(err.strip().splitlines()) == 1
