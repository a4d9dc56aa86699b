"""Measurement kind from the header: every contract kind, and a clear error otherwise."""

import pytest

from torchcal.data.kinds import measurement_kind
from torchcal.errors import DataError


@pytest.mark.parametrize(
    "header, kind",
    [
        ("q1,q2,q3,q4,q5,q6,x,y,z", "tracker"),
        ("q1,q2,q3,q4,q5,q6,l1,l2,l3,l4", "tracer"),
        ("q1,q2,q3,q4,q5,q6,fx,fy,fz,tx,ty,tz,dx,dy,dz,x,y,z", "stiffness"),
        ("scan,q1,q2,q3,q4,q5,q6,u,w,plane", "profile"),
        ("q1,q2,q3,q4,q5,q6,l1", "length_station"),
        ("placement,socket,q1,q2,q3,q4,q5,q6,q7", "sockets"),
    ],
)
def test_kind_from_header(tmp_path, header, kind):
    path = tmp_path / "m.csv"
    path.write_text(header + "\n" + ",".join("0" for _ in header.split(",")) + "\n")
    assert measurement_kind(path) == kind


def test_unknown_header_names_file_and_row(tmp_path):
    path = tmp_path / "odd.csv"
    path.write_text("q1,q2,a,b\n1,2,3,4\n")
    with pytest.raises(DataError, match=r"odd.csv, row 1: cannot tell the measurement kind"):
        measurement_kind(path)
