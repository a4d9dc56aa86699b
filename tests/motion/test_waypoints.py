import math

import pytest
import torch

from torchcal.core.errors import DataError
from torchcal.kinematics import transforms as tf
from torchcal.motion.waypoints import WaypointPath, load_waypoints, waypoints_csv

DEG = math.pi / 180.0
HEADER = "x,y,z,rx,ry,rz\n"


def _write(tmp_path, text, name="path.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_round_trip_and_euler_convention(tmp_path):
    path = _write(tmp_path, HEADER + "100,0,500,10,20,30\n400,0,500,10,20,30\n")
    wp = load_waypoints(path)
    assert wp.lines == (2, 3)
    # R = Rz(rz) Ry(ry) Rx(rx), built here from elementary rotations
    c = lambda a: math.cos(a * DEG)  # noqa: E731
    s = lambda a: math.sin(a * DEG)  # noqa: E731
    rx = torch.tensor([[1, 0, 0], [0, c(10), -s(10)], [0, s(10), c(10)]], dtype=torch.float64)
    ry = torch.tensor([[c(20), 0, s(20)], [0, 1, 0], [-s(20), 0, c(20)]], dtype=torch.float64)
    rz = torch.tensor([[c(30), -s(30), 0], [s(30), c(30), 0], [0, 0, 1]], dtype=torch.float64)
    torch.testing.assert_close(wp.poses[0, :3, :3], rz @ ry @ rx, rtol=0, atol=1e-14)
    torch.testing.assert_close(wp.poses[1, :3, 3], torch.tensor([0.4, 0.0, 0.5], dtype=torch.float64))
    again = load_waypoints(_write(tmp_path, waypoints_csv(wp.poses), "again.csv"))
    torch.testing.assert_close(again.poses, wp.poses, rtol=0, atol=1e-12)


@pytest.mark.parametrize("text, where", [
    ("x,y,z,rx,ry\n1,2,3,4,5\n2,2,3,4,5\n", "row 1: missing column 'rz'"),
    ("x,y,z,rx,ry,RZ\n1,2,3,4,5,6\n2,2,3,4,5,6\n", "(found 'RZ'"),
    ("x,y,z,rx,ry,rz,speed\n1,2,3,4,5,6,1\n2,2,3,4,5,6,1\n", "column 'speed'"),
    (HEADER + "1,2,3,4,5,6\n2,2,abc,4,5,6\n", "row 3, column 'z': 'abc' is not a number"),
    (HEADER + "1,2,3,4,5,6\n", "at least 2 waypoints"),
    (HEADER + "1,2,3,4,5,6\n1,2,3,4,5,6\n", "row 3: waypoint repeats the one on row 2"),
    (HEADER + "1,2,3,0,0,0\n2,2,3,0,0,180\n", "row 3, column 'rx': turns the tool by 180.00 deg"),
    (HEADER + "1,2,3,4,5,6\n2,2,3,4,5\n", "row 3: has 5 cells"),
])
def test_bad_files_name_file_row_and_column(tmp_path, text, where):
    path = _write(tmp_path, text)
    with pytest.raises(DataError) as info:
        load_waypoints(path)
    message = str(info.value)
    assert message.startswith(str(path)) and where in message and "\n" not in message


def test_path_lines_slerp_and_tangent():
    r0 = tf.euler_xyz_to_matrix(torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64))
    r1 = tf.euler_xyz_to_matrix(torch.tensor([0.3, 0.1, -0.4], dtype=torch.float64))
    poses = torch.stack([tf.homogeneous(r0, torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)),
                         tf.homogeneous(r1, torch.tensor([0.3, 0.4, 0.5], dtype=torch.float64)),
                         tf.homogeneous(r1, torch.tensor([0.3, 0.4, 0.5001], dtype=torch.float64))])
    path = WaypointPath(poses, speed=0.25, angular_speed=math.radians(90))
    angle = float(tf.so3_log(r1 @ r0.T).norm())
    # segment 1: the longer of the line and the turn at speed/angular_speed; segment 2: 0.1 mm line
    assert path.ell[0].item() == pytest.approx(max(0.5, angle * 0.25 / math.radians(90)))
    assert path.ell[1].item() == pytest.approx(1e-4)
    mid = path.poses_at(torch.tensor([0.5 * path.ell[0].item()], dtype=torch.float64))[0]
    torch.testing.assert_close(mid[:3, 3], torch.tensor([0.15, 0.2, 0.5], dtype=torch.float64))
    # slerp midpoint: equal angles to both ends, about the same axis
    a = tf.so3_log(mid[:3, :3] @ r0.T)
    b = tf.so3_log(r1 @ mid[:3, :3].T)
    torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    torch.testing.assert_close(path.poses_at(path.knots)[:, :3, 3], poses[:, :3, 3])
    # tangent = central finite difference of the poses
    s, h = torch.tensor([0.2], dtype=torch.float64), 1e-6
    plus, minus = path.poses_at(s + h)[0], path.poses_at(s - h)[0]
    fd = torch.cat([(plus[:3, 3] - minus[:3, 3]) / (2 * h), tf.so3_log(plus[:3, :3] @ minus[:3, :3].T) / (2 * h)])
    torch.testing.assert_close(path.tangent(s)[0], fd, rtol=1e-6, atol=1e-8)
