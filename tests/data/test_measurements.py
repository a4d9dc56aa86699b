"""Bad measurement input gets one clear error naming file, row and column."""

from __future__ import annotations

import math

import pytest
import torch

from torchcal.core.errors import DataError
from torchcal.data.measurements import load_measurements, write_measurements_csv

HEADER = "q1,q2,q3,q4,q5,q6,x,y,z"


def _good_rows(robot, n=30, seed=0):
    gen = torch.Generator().manual_seed(seed)
    q = robot.sample_joints(n, gen, margin=0.1)
    p = robot.tcp_position(q)
    return [",".join(f"{v:.6f}" for v in (qq * 180 / math.pi).tolist() + (pp * 1e3).tolist()) for qq, pp in zip(q, p)]


def _write(tmp_path, header, rows, name="m.csv"):
    path = tmp_path / name
    path.write_text("\n".join([header] + rows) + "\n")
    return path


def test_good_file_loads_in_si(robot, tmp_path, generator):
    q = robot.sample_joints(10, generator)
    p = robot.tcp_position(q)
    path = tmp_path / "ok.csv"
    write_measurements_csv(path, q, p)
    data = load_measurements(path, robot)
    assert torch.allclose(data.q, q, atol=1e-9)
    assert torch.allclose(data.position, p, atol=1e-12)
    assert len(data.sha256) == 64


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda h, r: (h.replace(",z", ""), [x.rsplit(",", 1)[0] for x in r]), r"missing column\(s\) \['z'\]"),
        (lambda h, r: (h + ",extra", [x + ",1" for x in r]), "unknown column 'extra'"),
        (lambda h, r: (h.replace(",x,", ",X,"), r), "did you mean 'x'"),
        (lambda h, r: (h, r[:3] + [r[3].replace(r[3].split(",")[7], "nan")] + r[4:]), r"row 5, column 'y': 'nan' is not a finite"),
        (lambda h, r: (h, r[:2] + [r[2].replace(r[2].split(",")[0], "abc", 1)] + r[3:]), r"row 4, column 'q1': 'abc' is not a number"),
        (lambda h, r: (h, r[:6] + [",".join([""] + r[6].split(",")[1:])] + r[7:]), r"row 8, column 'q1': empty cell"),
        (lambda h, r: (h, r[:1] + [",".join(r[1].split(",")[:1] + ["200"] + r[1].split(",")[2:])] + r[2:]), r"row 3, column 'q2'.*outside joint 2's limits"),
        (lambda h, r: (h, r + [r[4]]), r"duplicates row 6 exactly"),
        (lambda h, r: ("q1,q2,q3,q4,q5,q6,q7,x,y,z", [x.replace(",", ",0,", 1) for x in r]), "has 6 joints"),
        (lambda h, r: ("q1,q2,q3,q4,q5,x,y,z", [",".join(x.split(",")[:5] + x.split(",")[6:]) for x in r]), "has 6 joints"),
        (lambda h, r: (h, r[:2] + [r[2] + ",5"] + r[3:]), r"row 4: has 10 cells but the header has 9"),
        (lambda h, r: (h, []), "no data rows"),
        (lambda h, r: ("q1,q2,q3,q4,q5,q6,x,y,z,rx,ry", [x + ",0,0" for x in r]), "orientation needs all of rx, ry, rz"),
        (lambda h, r: ("q1,q2,q3,q4,q5,q6,x,x,z", r), "repeats column"),
        (lambda h, r: (h + ",temp", [x + (",-500" if k == 3 else ",21.5") for k, x in enumerate(r)]),
         r"row 5, column 'temp': temperature -500 deg C is outside"),
        (lambda h, r: (h + ",temp", [x + ",295.1" for x in r]), r"row 2, column 'temp'.*kelvin"),
    ],
    ids=["missing-column", "extra-column", "misnamed-column", "nan", "text", "empty-cell", "joint-limit",
         "duplicate-row", "too-many-joints", "too-few-joints", "ragged-row", "header-only", "partial-orientation",
         "duplicate-header", "below-absolute-zero", "kelvin"],
)
def test_bad_measurement_files(robot, tmp_path, mutate, match):
    header, rows = mutate(HEADER, _good_rows(robot))
    path = _write(tmp_path, header, rows)
    with pytest.raises(DataError, match=match) as info:
        load_measurements(path, robot)
    assert str(path) in str(info.value)


def test_empty_file_and_missing_file(robot, tmp_path):
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(DataError, match="empty"):
        load_measurements(empty, robot)
    with pytest.raises(DataError, match="not found"):
        load_measurements(tmp_path / "nope.csv", robot)


def test_too_few_poses_for_the_parameters(robot, tmp_path):
    from torchcal.identify.calibrate import calibrate

    path = _write(tmp_path, HEADER, _good_rows(robot, n=6))
    data = load_measurements(path, robot)
    with pytest.raises(DataError, match=r"6 poses give 18 equations \(3 per pose\), no more than the .* parameters"):
        calibrate(robot, data)


def test_cli_reports_one_line_without_traceback(robot, tmp_path, capsys):
    from torchcal.cli import main
    from torchcal.kinematics.robot import default_robot_path

    header, rows = HEADER, _good_rows(robot)
    rows[3] = rows[3].replace(rows[3].split(",")[7], "oops")
    path = _write(tmp_path, header, rows)
    code = main(["fit", "--robot", str(default_robot_path()), "--data", str(path), "--out", str(tmp_path / "m")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "row 5, column 'y'" in err[0] and "Traceback" not in err[0]
