"""A single length station refuses what its data cannot support, with the reason that applies.

Radians read as degrees, repeatability data (one joint configuration measured again and again),
a stuck sensor (constant column), and ``evaluate`` on small files: each is a one-line error naming
the file and the cause, or (for ``evaluate``) accepted when it has what evaluate itself needs.
"""

from __future__ import annotations

import csv
import json
import math
import warnings
from pathlib import Path

import pytest
import torch

from torchcal.cli import main
from torchcal.core.errors import DataError, IdentifiabilityWarning
from torchcal.instruments.tracer.data import TracerData, check_length_spread
from torchcal.instruments.tracer.one_station.data import count_configurations, load_length_data
from torchcal.instruments.tracer.one_station.fit import fit_station
from torchcal.instruments.tracer.one_station.twin import (
    LengthStationTwinConfig,
    write_length_station_case,
)
from torchcal.kinematics.robot import load_robot


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> dict[str, Path]:
    """A twin draw-wire case (40 fit rows, 15 test rows) and a model fitted on it."""
    root = tmp_path_factory.mktemp("length_station")
    files = write_length_station_case(root / "twin", LengthStationTwinConfig(n_train=40, n_test=15))
    files = {name: Path(p) for name, p in files.items()}
    model = root / "model"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["fit", "--robot", str(files["robot.yaml"]), "--data", str(files["lengths.csv"]),
                     "--out", str(model), "cv_folds=2", "max_iterations=30"]) == 0
    files["model"] = model
    return files


def _rows(path: Path) -> tuple[list[str], list[list[str]]]:
    rows = list(csv.reader(path.open()))
    return rows[0], rows[1:]


def _write(path: Path, header: list[str], rows: list[list[str]]) -> Path:
    with path.open("w", newline="") as f:
        csv.writer(f).writerows([header, *rows])
    return path


def _repeatability(case: dict[str, Path], path: Path, n: int = 30) -> Path:
    """One joint configuration of the fit file measured ``n`` times, readings scattered by 0.01 mm."""
    header, rows = _rows(case["lengths.csv"])
    first = rows[0]
    return _write(path, header, [first[:-1] + [repr(float(first[-1]) + 0.01 * ((i * 7) % 5 - 2))] for i in range(n)])


def _run(argv: list[str], capsys) -> tuple[int, str]:
    rc = main(argv)
    err = capsys.readouterr().err
    return rc, err


def _evaluate(case: dict[str, Path], data: Path, tmp_path: Path, *extra: str) -> dict:
    # a folder per evaluation: the one holding --json becomes that evaluation's run folder
    out = tmp_path / f"evaluation{sum(1 for _ in tmp_path.glob('evaluation*'))}" / "metrics.json"
    out.parent.mkdir()
    assert main(["evaluate", "--model", str(case["model"]), "--data", str(data), "--json", str(out), *extra]) == 0
    return json.loads(out.read_text())


# D3 -- joints in radians read as degrees


def test_joints_in_radians_read_as_degrees_are_refused_naming_the_option(case, tmp_path, capsys):
    header, rows = _rows(case["lengths.csv"])
    rad = _write(tmp_path / "rad.csv", header,
                 [[repr(math.radians(float(v))) for v in r[:-1]] + [r[-1]] for r in rows])
    with pytest.raises(DataError, match="the joints look like radians; set joint_unit=rad") as info:
        load_length_data(rad, load_robot(case["robot.yaml"]))
    assert info.value.path == str(rad) and info.value.row is not None and info.value.column.startswith("q")
    out = tmp_path / "m_rad"
    rc, err = _run(["fit", "--robot", str(case["robot.yaml"]), "--data", str(rad), "--out", str(out)], capsys)
    assert rc == 2 and "set joint_unit=rad" in err and err.count("\n") == 1 and not out.exists()
    rc, err = _run(["evaluate", "--model", str(case["model"]), "--data", str(rad)], capsys)
    assert rc == 2 and "set joint_unit=rad" in err
    # the same numbers read as radians load
    assert len(load_length_data(rad, load_robot(case["robot.yaml"]), joint_unit="rad")) == len(rows)


# D4 -- repeatability data: one configuration, many rows


def test_repeated_rows_count_as_one_configuration(case, tmp_path):
    data = load_length_data(case["lengths.csv"], load_robot(case["robot.yaml"]))
    assert count_configurations(data.q) == len(data) == 40
    doubled = torch.cat([data.q, data.q + 1e-9])
    assert count_configurations(doubled) == 40


def test_fit_refuses_repeatability_data_instead_of_inventing_parameters(case, tmp_path, capsys):
    path = _repeatability(case, tmp_path / "repeat.csv")
    out = tmp_path / "m_repeat"
    rc, err = _run(["fit", "--robot", str(case["robot.yaml"]), "--data", str(path), "--out", str(out)], capsys)
    assert rc == 2 and not out.exists()
    assert "1 distinct joint configuration(s) in 30 rows" in err and "repeatability" in err and str(path) in err
    assert err.count("\n") == 1 and "Traceback" not in err


def test_fit_station_refuses_lengths_that_cannot_determine_the_anchor(case):
    # past the loader (an API call): one configuration cannot give anchor and offset, and no
    # parameter confounded with them may come out "estimated" with a tiny sigma
    robot = load_robot(case["robot.yaml"])
    data = load_length_data(case["lengths.csv"], robot)
    q = data.q[:1].repeat(30, 1)
    lengths = data.lengths[:1] + 1e-5 * torch.arange(30, dtype=torch.float64).remainder(5).unsqueeze(-1)
    single = TracerData(q, lengths, "single.csv", tuple(range(2, 32)), "")
    with pytest.raises(DataError, match=r"cannot determine the anchor and offset: .*station1_x") as info:
        fit_station(robot, single, "nominal")
    assert info.value.path == "single.csv"


def test_a_structure_with_more_unknowns_than_configurations_keeps_the_rest_nominal(case):
    # a cross-validation fold of a 20-row file has 16 configurations, fewer than the full structure's
    # identifiable unknowns: the fit keeps one configuration to spare instead of failing on the covariance
    robot = load_robot(case["robot.yaml"])
    data = load_length_data(case["lengths.csv"], robot).subset(list(range(16)))
    with pytest.warns(IdentifiabilityWarning, match="16 distinct joint configurations support at most 15 unknowns"):
        fit = fit_station(robot, data, "full")
    assert len(fit.free) + 4 <= 15 and bool(torch.isfinite(fit.covariance).all())
    assert {"station1_x", "station1_y", "station1_z", "dead_path1", "tool_x", "tool_y", "tool_z"} <= set(
        fit.identifiability.base_set)


def test_evaluate_refuses_to_refit_the_anchor_from_one_configuration(case, tmp_path, capsys):
    path = _repeatability(case, tmp_path / "repeat.csv")
    rc, err = _run(["evaluate", "--model", str(case["model"]), "--data", str(path)], capsys)
    assert rc == 2 and "1 distinct joint configuration(s) in 30 rows" in err and "re-fit anchor and offset" in err
    # with the fitted anchor and offset kept, scoring repeated readings is meaningful
    assert _evaluate(case, path, tmp_path, "refit_anchor=false")["n_poses"] == 30


def test_evaluate_refuses_configurations_that_leave_the_anchor_undetermined(case, tmp_path, capsys):
    # only the last joint turns: the tool point runs on a circle, whose axis the anchor can slide along
    header, rows = _rows(case["test.csv"])
    first = rows[0]
    circle = _write(tmp_path / "circle.csv", header,
                    [first[:5] + [repr(float(first[5]) + 10.0 * i), repr(float(first[6]) + 0.001 * i)] for i in range(12)])
    rc, err = _run(["evaluate", "--model", str(case["model"]), "--data", str(circle)], capsys)
    assert rc == 2 and "cannot determine the anchor and offset that evaluate re-fits" in err and str(circle) in err


# D7 -- evaluate needs what it re-fits, not what a fit needs


def test_evaluate_accepts_small_files_it_can_score(case, tmp_path):
    header, rows = _rows(case["test.csv"])
    assert len(rows) == 15
    assert _evaluate(case, case["test.csv"], tmp_path, "refit_anchor=false")["n_poses"] == 15
    assert _evaluate(case, case["test.csv"], tmp_path)["n_poses"] == 15
    ten = _write(tmp_path / "ten.csv", header, rows[:10])
    metrics = _evaluate(case, ten, tmp_path)
    assert metrics["n_poses"] == 10 and metrics["registered"] and metrics["length_rms_mm"] < 0.5
    one = _write(tmp_path / "one.csv", header, rows[:1])
    assert _evaluate(case, one, tmp_path, "refit_anchor=false")["n_poses"] == 1


def test_evaluate_names_its_own_reason_for_too_few_configurations(case, tmp_path, capsys):
    header, rows = _rows(case["test.csv"])
    nine = _write(tmp_path / "nine.csv", header, rows[:9])
    for extra in ([], ["--register"]):
        rc, err = _run(["evaluate", "--model", str(case["model"]), "--data", str(nine), *extra], capsys)
        assert rc == 2 and "9 distinct joint configuration(s) are too few for evaluate to re-fit anchor and offset" in err
        assert "needs at least 10" in err and "refit_anchor=false" in err and "cross-validation" not in err


def test_fit_still_needs_twenty_configurations(case, tmp_path, capsys):
    header, rows = _rows(case["lengths.csv"])
    few = _write(tmp_path / "few.csv", header, rows[:19])
    rc, err = _run(["fit", "--robot", str(case["robot.yaml"]), "--data", str(few), "--out", str(tmp_path / "m")], capsys)
    assert rc == 2 and "19 distinct joint configuration(s) are too few for a length-station fit" in err


# D11 -- a constant length column is a stuck sensor, not a unit mistake


@pytest.mark.parametrize("unit", ["mm", "m"])
def test_a_constant_length_column_is_called_a_stuck_sensor(case, tmp_path, capsys, unit):
    header, rows = _rows(case["lengths.csv"])
    stuck = _write(tmp_path / "stuck.csv", header, [r[:-1] + ["700.0"] for r in rows])
    with pytest.raises(DataError, match=r"every one of its 40 readings is 700 \w+: the column is constant") as info:
        load_length_data(stuck, load_robot(case["robot.yaml"]), length_unit=unit)
    assert info.value.path == str(stuck) and info.value.column == "l1"
    assert "stuck or disconnected sensor" in str(info.value) and "length_unit=" not in str(info.value)
    rc, err = _run(["fit", "--robot", str(case["robot.yaml"]), "--data", str(stuck), "--out", str(tmp_path / "m"),
                    f"length_unit={unit}"], capsys)
    assert rc == 2 and "the column is constant" in err and "look like metres" not in err


def test_a_mostly_constant_column_is_called_a_stuck_sensor(case, tmp_path):
    header, rows = _rows(case["lengths.csv"])
    stuck = _write(tmp_path / "mostly.csv", header, [r[:-1] + ["700.0" if i < 30 else r[-1]] for i, r in enumerate(rows)])
    with pytest.raises(DataError, match="30 of its 40 readings are 700 mm: the column is mostly constant"):
        load_length_data(stuck, load_robot(case["robot.yaml"]))


def test_a_stuck_station_of_a_tracer_is_named(case):
    # the shared spread check: a constant station among moving ones is named, not hidden behind the widest
    robot = load_robot(case["robot.yaml"])
    data = load_length_data(case["lengths.csv"], robot)
    lengths = torch.cat([data.lengths, data.lengths + 0.1, torch.full_like(data.lengths, 0.7)], 1)
    tracer = TracerData(data.q, lengths, "tracer.csv", data.line_numbers, "")
    with pytest.raises(DataError, match="column 'l3': every one of its 40 readings is 700 mm"):
        check_length_spread(tracer, robot, "mm")
