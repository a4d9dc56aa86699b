"""Stiffness file loader: round trip with the twin's writer, and every bad-input case."""

from __future__ import annotations

import math

import pytest
import torch
from helpers import write_file

from torchcal.core.errors import DataError
from torchcal.instruments.stiffness.data import load_stiffness
from torchcal.instruments.stiffness.twin import (
    StiffnessTwin,
    StiffnessTwinConfig,
    write_stiffness_csv,
)

HEADER = "q1,q2,q3,q4,q5,q6,fx,fy,fz,tx,ty,tz,dx,dy,dz"
ROW = "10,-20,30,0,45,90,100,0,-50,1,2,3,0.1,-0.2,0.3"


def _write(tmp_path, text, name="s.csv"):
    return write_file(tmp_path, text, name)


def test_round_trip_with_the_twin_writer(tmp_path):
    twin = StiffnessTwin(StiffnessTwinConfig(seed=2))
    data = twin.sample(15, torch.Generator().manual_seed(0))
    path = write_stiffness_csv(tmp_path / "rig.csv", data)
    back = load_stiffness(path, n_joints=6)
    assert back.path == str(path) and len(back) == 15 and back.n_joints == 6
    for a, b in [(data.q, back.q), (data.wrench, back.wrench), (data.deflection, back.deflection),
                 (data.rotation, back.rotation), (data.unloaded, back.unloaded)]:
        torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-15)


def test_units_and_optional_groups(tmp_path):
    path = _write(tmp_path, HEADER + "\n" + ROW + "\n")
    data = load_stiffness(path)
    assert data.rotation is None and data.unloaded is None
    assert math.isclose(float(data.q[0, 0]), math.radians(10))
    assert math.isclose(float(data.deflection[0, 2]), 0.3e-3)
    torch.testing.assert_close(data.wrench[0], torch.tensor([100.0, 0, -50, 1, 2, 3], dtype=torch.float64))
    # the conversion alone: 0.3 m is no plausible deflection (refused, see test_stiffness_units.py)
    rad = load_stiffness(path, joint_unit="rad", length_unit="m", check_plausible=False)
    assert float(rad.q[0, 0]) == 10.0 and float(rad.deflection[0, 2]) == 0.3
    full = _write(tmp_path, HEADER + ",drx,dry,drz,x,y,z\n" + ROW + ",0.01,0,0,1000,2000,500\n", "full.csv")
    data = load_stiffness(full)
    assert math.isclose(float(data.rotation[0, 0]), math.radians(0.01)) and float(data.unloaded[0, 1]) == 2.0


@pytest.mark.parametrize(
    "text, match, row, column",
    [
        ("", "empty", None, None),
        (HEADER + "\n", "no data rows", None, None),
        (HEADER.replace(",dz", "") + "\n" + ROW.rsplit(",", 1)[0] + "\n", r"missing column\(s\) \['dz'\]", 1, "dz"),
        (HEADER.replace(",fy", "") + "\n" + ROW.replace(",0,-50", ",-50") + "\n", r"\['fy'\]", 1, "fy"),
        (HEADER + ",drx,dry\n" + ROW + ",0,0\n", "rotation needs all", 1, "drz"),
        (HEADER + ",x,y\n" + ROW + ",1,2\n", "unloaded position needs all", 1, "z"),
        (HEADER + ",temp\n" + ROW + ",20\n", "unknown column 'temp'", 1, "temp"),
        (HEADER + "\n" + ROW + "\n" + ROW.replace("45", "abc") + "\n", "'abc' is not a number", 3, "q5"),
        (HEADER + "\n" + ROW.replace("-0.2", "") + "\n", "empty cell", 2, "dy"),
        (HEADER + "\n" + ROW.replace("-0.2", "inf") + "\n", "not a finite number", 2, "dy"),
        (HEADER + "\n" + ROW.replace("-0.2", "nan") + "\n", "not a finite number", 2, "dy"),
        (HEADER + "\n" + ROW + ",7\n", "has 16 cells but the header has 15", 2, None),
        (HEADER + "\n\n" + "10,-20,30,0,45,90,0,0,0,0,0,0,0.1,-0.2,0.3\n", "wrench is zero", 3, "fx"),
        (HEADER.replace("q3", "q7") + "\n" + ROW + "\n", "without gaps", 1, None),
        (HEADER.replace("dx", "dy") + "\n" + ROW + "\n", "repeats", 1, "dy"),
        ("fx,fy,fz,tx,ty,tz,dx,dy,dz\n100,0,0,0,0,0,1,1,1\n", "no joint columns", 1, None),
    ],
    ids=["empty", "header-only", "missing-dz", "missing-fy", "partial-rotation", "partial-xyz", "unknown",
         "not-a-number", "empty-cell", "inf", "nan", "ragged", "zero-wrench", "gap", "duplicate", "no-joints"],
)
def test_bad_files_name_file_row_and_column(tmp_path, text, match, row, column):
    path = _write(tmp_path, text)
    with pytest.raises(DataError, match=match) as info:
        load_stiffness(path)
    err = info.value
    assert err.path == str(path) and str(path) in str(err)
    assert err.row == row and err.column == column


def test_wrong_joint_count_missing_file_and_bad_units(tmp_path):
    path = _write(tmp_path, HEADER + "\n" + ROW + "\n")
    with pytest.raises(DataError, match="6 joint columns but the robot has 7"):
        load_stiffness(path, n_joints=7)
    with pytest.raises(DataError, match="file not found"):
        load_stiffness(tmp_path / "absent.csv")
    with pytest.raises(DataError, match="joint_unit"):
        load_stiffness(path, joint_unit="grad")
    with pytest.raises(DataError, match="length_unit"):
        load_stiffness(path, length_unit="inch")
    binary = tmp_path / "b.csv"
    binary.write_bytes(b"\xff\xfe\x00q1")
    with pytest.raises(DataError, match="UTF-8"):
        load_stiffness(binary)
