"""Socket files: kind sniffing, validation errors naming file, row and column."""

from __future__ import annotations

import pytest
from helpers import write_file

from torchcal.core.errors import DataError
from torchcal.instruments.registry import recognise
from torchcal.instruments.sockets.data import load_socket_data
from torchcal.kinematics.robot import default_robot_path, load_robot

HEADER = "placement,socket,q1,q2,q3,q4,q5,q6\n"
ROW = "front,{s},10,-20,30,5,40,6\n"


def _write(tmp_path, text):
    return write_file(tmp_path, text, "s.csv")


def test_header_with_placement_and_socket_is_the_sockets_kind(tmp_path):
    assert recognise(_write(tmp_path, HEADER + ROW.format(s=0))).name == "sockets"


def test_groups_and_pairs_and_degrees(tmp_path):
    robot = load_robot(default_robot_path())
    data = load_socket_data(_write(tmp_path, HEADER + ROW.format(s=0) * 2 + ROW.format(s=1) * 2), robot)
    assert data.groups == (("front", 0), ("front", 1))
    assert data.pairs() == [("front", 0, 1)]
    assert abs(float(data.q[0, 0]) - 10 * 3.141592653589793 / 180) < 1e-12


def test_a_bad_socket_cell_names_file_row_and_column(tmp_path):
    robot = load_robot(default_robot_path())
    path = _write(tmp_path, HEADER + ROW.format(s=0) * 2 + "front,one,1,2,3,4,5,6\n")
    with pytest.raises(DataError, match=r"s\.csv, row 4, column 'socket'"):
        load_socket_data(path, robot)


def test_a_missing_column_and_a_lonely_socket_are_errors(tmp_path):
    robot = load_robot(default_robot_path())
    with pytest.raises(DataError, match="missing column 'socket'"):
        load_socket_data(_write(tmp_path, "placement,q1,q2,q3,q4,q5,q6\nA,1,2,3,4,5,6\n"), robot)
    with pytest.raises(DataError, match=r"row 4, column 'socket'.*1 row"):
        load_socket_data(_write(tmp_path, HEADER + ROW.format(s=0) * 2 + ROW.format(s=1)), robot)
