"""Stiffness files in the wrong unit: one line naming file, columns and likely unit, never a traceback.

Each case scales some columns of a twin file by a unit factor (as a user's export in kN, N mm, m,
um or rad would be) and gives it to ``fit`` and ``evaluate``; the plausibility ranges of
:mod:`torchcal.instruments.stiffness.data` must name the unit mistake.
"""

from __future__ import annotations

import csv
import json
import math
from types import SimpleNamespace

import pytest
from helpers import write_file

from torchcal.cli import main
from torchcal.core.errors import DataError
from torchcal.instruments.stiffness.data import load_stiffness
from torchcal.stages.base import StiffnessStage

HEADER = "q1,q2,q3,q4,q5,q6,fx,fy,fz,tx,ty,tz,dx,dy,dz"

#: name -> (columns, factor, columns the message names, likely unit)
MISTAKES = {
    "forces-kN": (("fx", "fy", "fz"), 1e-3, "fx, fy, fz", "the forces look like kN"),
    "wrench-kN": (("fx", "fy", "fz", "tx", "ty", "tz"), 1e-3, "fx, fy, fz", "the wrenches look like kN and kN m"),
    "torques-Nmm": (("tx", "ty", "tz"), 1e3, "tx, ty, tz", "the moments look like N mm"),
    "deflections-m": (("dx", "dy", "dz"), 1e-3, "dx, dy, dz", "the deflections look like m"),
    "deflections-um": (("dx", "dy", "dz"), 1e3, "dx, dy, dz", "the deflections look like um"),
    "rotations-rad": (("drx", "dry", "drz"), math.pi / 180.0, "drx, dry, drz", "the rotations look like rad"),
}


def _scaled(source, target, factor: float, columns) -> None:
    """Copy the CSV ``source`` to ``target`` with ``columns`` multiplied by ``factor``."""
    with open(source, newline="") as handle:
        rows = list(csv.reader(handle))
    index = {rows[0].index(c) for c in columns}
    with open(target, "w", newline="") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(rows[0])
        for row in rows[1:]:
            writer.writerow([repr(float(v) * factor) if j in index and v else v for j, v in enumerate(row)])


def _one_error_line(err: str) -> str:
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert "Traceback" not in err and len(lines) == 1, err
    return lines[0]




@pytest.mark.parametrize("mistake", list(MISTAKES))
def test_fit_refuses_a_wrong_unit_in_one_line(case, tmp_path, capsys, mistake):
    columns, factor, named, hint = MISTAKES[mistake]
    path = tmp_path / f"{mistake}.csv"
    _scaled(case / "stiffness_train.csv", path, factor, columns)
    capsys.readouterr()
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(path), "--out", str(tmp_path / "m")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(path) in line and named in line and hint in line
    assert not (tmp_path / "m").exists()


@pytest.mark.parametrize("mistake", ["forces-kN", "wrench-kN", "deflections-m"])
def test_evaluate_refuses_a_wrong_unit_in_one_line(case, fitted, tmp_path, capsys, mistake):
    """Before: a wrench in kN scored deflection_ratio 0.985 with exit 0 and no warning."""
    columns, factor, named, hint = MISTAKES[mistake]
    path = tmp_path / f"{mistake}.csv"
    _scaled(case / "stiffness_test.csv", path, factor, columns)
    capsys.readouterr()
    out = tmp_path / "e.json"
    assert main(["evaluate", "--model", str(fitted), "--data", str(path), "--json", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(path) in line and named in line and hint in line
    assert not out.exists()
    # the file as it is, in the contract's units, is scored
    assert main(["evaluate", "--model", str(fitted), "--data", str(case / "stiffness_test.csv"), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["deflection_ratio"] < 0.2


def test_length_unit_m_on_a_mm_file_is_refused(case, tmp_path, capsys):
    args = ["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "stiffness_train.csv"), "--out", str(tmp_path / "m")]
    assert main(args + ["length_unit=m"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "dx, dy, dz" in line and "look like mm; set length_unit=mm" in line


def test_check_plausible_false_fits_and_reports_unbounded_sigmas(case, tmp_path):
    """The escape hatch: the kN file is fitted as given; the stiffnesses it drives to the rigid
    bound have no sigma (``null`` in stiffness.json), which the report shows as n/a (the report
    table used to crash on them)."""
    path = tmp_path / "kN.csv"
    _scaled(case / "stiffness_train.csv", path, 1e-3, ("fx", "fy", "fz"))
    model = tmp_path / "m"
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(path), "--out", str(model),
                 "check_plausible=false"]) == 0
    parameters = json.loads((model / "stiffness.json").read_text())["parameters"]
    assert any(p["sigma"] is None for p in parameters.values())
    assert "| n/a |" in (model / "report.md").read_text()


def test_report_table_formats_missing_numbers():
    stiffness = SimpleNamespace(metadata={"parameters": {
        "k_j1_rz": {"value": 2.5e5, "unit": "N m/rad", "sigma": 1.25e3, "status": "identified"},
        "k_j2_rx": {"value": None, "unit": "N m/rad", "sigma": None, "status": "at_rigid_bound"},
        "k_j3_rz": {"unit": "N m/rad"},
    }})
    table = StiffnessStage(stiffness, None, None).report_table()  # type: ignore[arg-type]  # reads only metadata
    assert table is not None
    assert table.rows == [
        ["k_j1_rz", "250000", "N m/rad", "1.25e+03", "identified"],
        ["k_j2_rx", "n/a", "N m/rad", "n/a", "at_rigid_bound"],
        ["k_j3_rz", "n/a", "N m/rad", "n/a", ""],
    ]


@pytest.mark.parametrize(
    "row, match, column",
    [
        ("10,-20,30,0,45,90,0.1,0,-0.05,0.001,0.002,0.003,0.1,-0.2,0.3", "wrenches look like kN and kN m", "fx"),
        ("10,-20,30,0,45,90,60000,0,0,0,0,0,0.1,-0.2,0.3", "check their unit", "fx"),
        ("10,-20,30,0,45,90,0,0,0,0,0,30000,0.1,-0.2,0.3", "moments look like N mm", "tz"),
        ("10,-20,30,0,45,90,100,0,0,0,0,0,0.0001,0,0.002", "deflections look like m", "dz"),
        ("10,-20,30,0,45,90,100,0,0,0,0,0,100,0,300", "deflections look like um", "dz"),
    ],
    ids=["wrench-kN", "force-too-large", "pure-moment-Nmm", "deflection-m", "deflection-um"],
)
def test_loader_names_row_column_and_unit(tmp_path, row, match, column):
    path = write_file(tmp_path, HEADER + "\n" + row + "\n", "s.csv")
    with pytest.raises(DataError, match=match) as info:
        load_stiffness(path)
    assert info.value.path == str(path) and info.value.row == 2 and info.value.column == column
    assert len(load_stiffness(path, check_plausible=False)) == 1


def test_plausible_edge_files_load(tmp_path):
    """A pure-moment load (no force) and small but resolvable loads of a stiff arm are accepted."""
    rows = ["10,-20,30,0,45,90,0,0,0,0,0,40,0.01,-0.02,0.03", "10,-20,30,0,45,90,20,0,0,0,0,0,0.006,0,0"]
    path = write_file(tmp_path, HEADER + "\n" + "\n".join(rows) + "\n", "edge.csv")
    assert len(load_stiffness(path)) == 2
