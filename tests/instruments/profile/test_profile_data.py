"""Profile-scan loader: round trip with the twin's writer, units, labels, and every bad-input case."""

from __future__ import annotations

import math

import pytest
import torch
from helpers import write_file

from torchcal.core.errors import DataError
from torchcal.instruments.profile.data import load_profile, write_profile_csv
from torchcal.instruments.profile.twin import ProfileTwin, ProfileTwinConfig

HEADER = "scan,q1,q2,q3,q4,q5,q6,u,w,plane"
Q = "10,-60,80,0,45,90"


def _write(tmp_path, text, name="p.csv"):
    return write_file(tmp_path, text, name)


def test_round_trip_with_the_twin_writer(tmp_path, robot):
    data = ProfileTwin(ProfileTwinConfig(seed=1, points_per_scan=30)).scan()
    path = write_profile_csv(tmp_path / "profile.csv", data)
    back = load_profile(path, n_joints=6, joint_limits_rad=robot.joint_limits)
    assert (back.n_scans, back.n_points, back.n_planes) == (data.n_scans, data.n_points, data.n_planes)
    torch.testing.assert_close(back.q, data.q, rtol=0, atol=1e-13)
    torch.testing.assert_close(back.uw, data.uw, rtol=0, atol=1e-12)
    assert torch.equal(back.point_scan, data.point_scan) and torch.equal(back.plane, data.plane)
    assert back.scan_lines[0] == 2 and back.sha256 is not None


def test_units_labels_and_optional_plane(tmp_path):
    text = "scan,q1,q2,q3,q4,q5,q6,u,w\n" + "".join(f"7,{Q},{u},{100 + u}\n" for u in (-1, 0, 2))
    data = load_profile(_write(tmp_path, text))
    assert data.n_planes == 1 and data.plane_labels == ("0",) and data.scan_labels == ("7",)
    assert math.isclose(float(data.q[0, 0]), math.radians(10)) and math.isclose(float(data.uw[2, 1]), 0.102)
    raw = load_profile(_write(tmp_path, text, "r.csv"), joint_unit="rad", length_unit="m")
    assert float(raw.q[0, 0]) == 10.0 and float(raw.uw[2, 1]) == 102.0
    # scan labels restart per placement: a scan is its (plane, scan) pair; '2.0' is label '2'
    rows = [f"0,{Q},0,100,2", f"0,{Q},1,101,2.0", "0,1,2,3,4,5,6,0,100,5", "0,1,2,3,4,5,6,1,101,5"]
    data = load_profile(_write(tmp_path, HEADER + "\n" + "\n".join(rows) + "\n", "l.csv"))
    assert data.n_scans == 2 and data.plane_labels == ("2", "5") and data.plane.tolist() == [0, 1]


@pytest.mark.parametrize(
    "text, match, row, column",
    [
        ("scan,q1,q2,q3,q4,q5,q6,u\n" + f"0,{Q},1\n", "missing column 'w'", 1, "w"),
        ("Scan,q1,q2,q3,q4,q5,q6,u,w\n" + f"0,{Q},1,2\n", "case-sensitive", 1, "scan"),
        (HEADER + ",x\n" + f"0,{Q},1,2,0,5\n", "unknown column 'x'", 1, "x"),
        ("scan,q1,q2,q4,q5,q6,q7,u,w\n" + f"0,{Q},1,2\n", "without gaps", 1, None),
        (HEADER + "\n" + f"0,{Q},,2,0\n", "empty cell", 2, "u"),
        (HEADER + "\n" + f"0,{Q},1,abc,0\n", "not a number", 2, "w"),
        (HEADER + "\n" + f"0,{Q},1,inf,0\n", "not a finite", 2, "w"),
        (HEADER + "\n" + f"1.5,{Q},1,2,0\n", "integer label", 2, "scan"),
        (HEADER + "\n" + f"0,{Q},1,2,x\n", "integer label", 2, "plane"),
        (HEADER + "\n" + f"0,{Q},1,2,0\n0,10,-60,80,0,45.5,90,2,3,0\n", "share its robot pose", 3, "q5"),
        (HEADER + "\n" + f"0,{Q},1,2,0\n0,{Q},1,2,0\n", "single distinct point", 2, "u"),
        (HEADER + "\n" + f"0,{Q},1,2,0\n1,{Q},1,2,0\n1,{Q},2,3,0\n", "has one point", 2, "u"),
        (HEADER + "\n" + "0,175,-60,80,0,45,90,1,2,0\n0,175,-60,80,0,45,90,2,3,0\n", "outside joint 1", 2, "q1"),
    ],
)
def test_bad_input_names_file_row_and_column(tmp_path, robot, text, match, row, column):
    path = _write(tmp_path, text)
    with pytest.raises(DataError, match=match) as info:
        load_profile(path, n_joints=6, joint_limits_rad=robot.joint_limits)
    assert info.value.path == str(path) and info.value.row == row and info.value.column == column


def test_joint_count_and_units_are_checked(tmp_path):
    path = _write(tmp_path, "scan,q1,q2,u,w\n0,1,2,3,4\n0,1,2,4,5\n")
    with pytest.raises(DataError, match="robot has 6 joints"):
        load_profile(path, n_joints=6)
    with pytest.raises(DataError, match="joint_unit"):
        load_profile(path, joint_unit="grad")
