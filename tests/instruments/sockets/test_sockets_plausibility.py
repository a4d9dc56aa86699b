"""Socket fits and evaluations refuse data that cannot calibrate the robot: one line, exit 2, nothing written."""

from __future__ import annotations

import csv
import json
import math
import warnings

import pytest

from torchcal.cli import main
from torchcal.instruments.sockets.twin import SocketsTwinConfig, write_sockets_case


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """Twin with 12 configurations per socket: fixture1, fixture2 in sockets.csv, fixture3 in sockets_test.csv."""
    out = tmp_path_factory.mktemp("sockets_plausible")
    return write_sockets_case(out, SocketsTwinConfig(n_placements=2, n_test_placements=1, configurations_per_socket=12))


def _rows(path):
    rows = list(csv.reader(path.open(newline="")))
    return rows[0], rows[1:]


def _write(path, header, rows):
    with path.open("w", newline="") as f:
        csv.writer(f).writerows([header, *rows])
    return path


def _fit(case, data, out, *extra):
    return main(["fit", "--robot", str(case["robot.yaml"]), "--data", str(data), "--out", str(out), *extra])


def _subset(case, tmp_path, per_socket, placements=("fixture1",)):
    header, rows = _rows(case["sockets.csv"])
    picked = [r for p in placements for s in ("0", "1") for r in [r for r in rows if r[:2] == [p, s]][:per_socket]]
    return _write(tmp_path / f"s{per_socket}.csv", header, picked)


@pytest.mark.parametrize("per_socket, placements, message", [
    (3, ("fixture1",), "6 configurations give 19 equations"),
    (2, ("fixture1",), "4 configurations give 13 equations"),
    (2, ("fixture1", "fixture2"), "8 configurations give 26 equations"),
])
def test_too_few_configurations_are_refused_before_the_fit(case, tmp_path, capsys, per_socket, placements, message):
    """Used to crash in identify/uncertainty.py (no covariance from as many residuals as parameters)."""
    data = _subset(case, tmp_path, per_socket, placements)
    assert _fit(case, data, tmp_path / "m") == 2
    err = capsys.readouterr().err
    assert message in err and "unknowns" in err and "record at least" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "m").exists()


def test_just_enough_configurations_warn_that_the_fit_follows_the_noise(case, tmp_path):
    """5 per socket used to fit silently to 0.004 mm on its own rows (the noise)."""
    data = _subset(case, tmp_path, 5)
    with pytest.warns(UserWarning, match=r"10 configurations give 31 equations for 25 unknowns .*follows the noise"):
        assert _fit(case, data, tmp_path / "m") == 0
    notes = json.loads((tmp_path / "m" / "calibration.json").read_text())["notes"]
    assert any("the fit follows the noise" in n for n in notes)


def test_enough_configurations_fit_without_that_warning(case, tmp_path):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert _fit(case, case["sockets.csv"], tmp_path / "m") == 0
    assert caught and not [w for w in caught if "follows the noise" in str(w.message)]


def test_radians_read_as_degrees_are_refused_by_fit_and_evaluate(case, tmp_path, capsys):
    header, rows = _rows(case["sockets.csv"])
    data = _write(tmp_path / "rad.csv", header, [r[:2] + [f"{math.radians(float(v)):.9f}" for v in r[2:]] for r in rows])
    assert _fit(case, data, tmp_path / "bad") == 2
    assert "look like radians; set joint_unit=rad" in capsys.readouterr().err
    assert _fit(case, case["sockets.csv"], tmp_path / "m") == 0
    capsys.readouterr()
    assert main(["evaluate", "--model", str(tmp_path / "m"), "--data", str(data), "--json", str(tmp_path / "e.json")]) == 2
    assert "look like radians" in capsys.readouterr().err
    assert not (tmp_path / "e.json").exists()


def test_distance_in_metres_is_refused(case, tmp_path, capsys):
    assert _fit(case, case["sockets.csv"], tmp_path / "m", "distance_mm=0.05") == 2
    err = capsys.readouterr().err
    assert "distance_mm looks like metres (distance_mm=50?)" in err and "column 'socket'" in err


def test_two_placements_under_one_name_are_refused_naming_the_rows(case, tmp_path, capsys):
    header, rows = _rows(case["sockets.csv"])
    merged = _write(tmp_path / "merged.csv", header, [["fixture1", *r[1:]] for r in rows])
    assert _fit(case, merged, tmp_path / "m") == 2
    err = capsys.readouterr().err
    # fixture1/0 is on lines 2-13, fixture2/0 (renamed) on 26-37
    assert "row 26" in err and "rows 2-13 and 26-37" in err and "two placements under one name" in err


def test_joints_of_another_robot_are_refused(case, tmp_path, capsys):
    """Joint columns in another order stand for a file of another robot: the nominal ball centres scatter."""
    header, rows = _rows(case["sockets.csv"])
    swapped = _write(tmp_path / "swapped.csv", header, [r[:2] + [r[3], r[2], r[5], r[4], *r[6:]] for r in rows])
    assert _fit(case, swapped, tmp_path / "m", "check_limits=false") == 2
    err = capsys.readouterr().err
    assert "mm (mean) from their common point" in err and "wrong robot file" in err
    assert not (tmp_path / "m").exists()


def test_a_fit_worse_than_the_nominal_robot_is_refused(case, tmp_path, capsys):
    """A third fixture 69 mm wide declared 50 mm: the fit trades consistency for the distances (1.06 -> 1.14 mm)."""
    wide = write_sockets_case(tmp_path / "wide", SocketsTwinConfig(n_placements=1, n_test_placements=1,
                                                                    configurations_per_socket=12, distance_mm=69.0))
    header, rows = _rows(case["sockets.csv"])
    _, extra = _rows(wide["sockets.csv"])
    data = _write(tmp_path / "contra.csv", header, rows + [["wide", *r[1:]] for r in extra])
    assert _fit(case, data, tmp_path / "m") == 2
    err = capsys.readouterr().err
    assert "misses its own configurations by more than the nominal one" in err and "nothing written" in err
    assert not (tmp_path / "m").exists()
