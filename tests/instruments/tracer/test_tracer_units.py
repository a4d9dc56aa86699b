"""Tracer and one-station length files in the wrong unit or with a gap in l1..lM: one clear line, no model."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch

from torchcal.cli import main
from torchcal.core.errors import DataError
from torchcal.instruments.tracer.data import load_tracer_data
from torchcal.instruments.tracer.one_station.data import load_length_data
from torchcal.instruments.tracer.twin_case import (
    TracerTwinConfig,
    simulate_tracer_case,
    write_lengths_csv,
)
from torchcal.kinematics.robot import load_robot


@pytest.fixture(scope="module")
def tracer_case(tmp_path_factory):
    """A simulated tracer case on disk: robot.yaml and lengths.csv (deg, mm)."""
    folder = tmp_path_factory.mktemp("tcase")
    assert main(["simulate", "--out", str(folder), "instrument=tracer", "n_train=24", "n_test=4", "seed=3"]) == 0
    return folder


def _scaled(source: Path, target: Path, factor: float, columns: tuple[str, ...]) -> Path:
    """``source`` with ``columns`` multiplied by ``factor`` (empty cells stay empty)."""
    rows = list(csv.reader(source.open()))
    index = [rows[0].index(c) for c in columns]
    out = [rows[0]] + [[repr(float(v) * factor) if j in index and v else v for j, v in enumerate(r)] for r in rows[1:]]
    target.write_text("\n".join(",".join(r) for r in out) + "\n")
    return target


def _one_line_error(capsys, argv: list[str], *needles: str) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, err
    return err


def test_tracer_lengths_in_metres_are_refused_not_fitted_to_a_tiny_robot(tmp_path, tracer_case, capsys):
    data = _scaled(tracer_case / "lengths.csv", tmp_path / "trm.csv", 1e-3, ("l1", "l2", "l3", "l4"))
    out = tmp_path / "trm"
    _one_line_error(capsys, ["fit", "--robot", str(tracer_case / "robot.yaml"), "--data", str(data), "--out", str(out)],
                    "trm.csv", "column 'l", "the lengths look like metres; set length_unit=m")
    assert not (out / "calibration.json").exists()
    # the same file read in metres is the correct one
    robot = load_robot(tracer_case / "robot.yaml")
    si = load_tracer_data(data, robot, length_unit="m")
    mm = load_tracer_data(tracer_case / "lengths.csv", robot)
    torch.testing.assert_close(si.lengths.nan_to_num(), mm.lengths.nan_to_num(), atol=1e-9, rtol=0)


def test_a_gap_in_the_station_columns_is_refused_naming_the_column(tmp_path, tracer_case, capsys):
    # q1..q6, l1, l3: no l2, so it is recognised as one station; l3 must not be silently dropped
    rows = [line.split(",") for line in (tracer_case / "lengths.csv").read_text().splitlines()]
    gap = tmp_path / "gap.csv"
    gap.write_text("\n".join(",".join(r[:7] + [r[8]]) for r in rows) + "\n")
    out = tmp_path / "g"
    err = _one_line_error(capsys, ["fit", "--robot", str(tracer_case / "robot.yaml"), "--data", str(gap), "--out", str(out)],
                          "gap.csv", "column 'l3'", "l1..lM without gaps", "'l3' without 'l2'")
    assert "row 1" in err and not out.exists()
    with pytest.raises(DataError, match="'l3' without 'l2'") as info:
        load_length_data(gap, load_robot(tracer_case / "robot.yaml"))
    assert (info.value.row, info.value.column) == (1, "l3")


def test_a_gap_after_l2_names_the_first_column_past_it(tmp_path, tracer_case):
    robot = load_robot(tracer_case / "robot.yaml")
    header = [f"q{i}" for i in range(1, 7)] + ["l1", "l2", "l4", "l5"]
    path = tmp_path / "h.csv"
    path.write_text(",".join(header) + "\n" + ",".join("1" for _ in header) + "\n")
    with pytest.raises(DataError, match="'l4' without 'l3'") as info:
        load_tracer_data(path, robot)
    assert info.value.column == "l4"


@pytest.mark.parametrize("factor, unit, hint", [
    (1e-3, "mm", "the lengths look like metres; set length_unit=m"),
    (1.0, "m", "the lengths look like millimetres; set length_unit=mm"),
])
def test_one_station_lengths_in_the_wrong_unit_are_refused(tmp_path, factor, unit, hint):
    case = simulate_tracer_case(TracerTwinConfig(seed=5, n_train=24, n_test=4))
    path = tmp_path / "one.csv"
    write_lengths_csv(path, case.q_train, case.lengths[:, :1] * factor)
    with pytest.raises(DataError, match=hint) as info:
        load_length_data(path, case.twin.robot, length_unit=unit)
    assert info.value.column == "l1" and info.value.path == str(path)
    # the correct unit loads: a draw-wire's readings spread like the TCP does
    ok = load_length_data(path, case.twin.robot, length_unit="m" if unit == "mm" else "mm")
    assert math.isclose(float(ok.lengths[3, 0]), float(case.lengths[3, 0]), abs_tol=1e-6)  # 7 decimals written


def test_a_single_wrong_reading_is_left_to_the_triangle_inequality(tmp_path):
    # the spread is a median: one lost count is named by its row, not taken for a unit mistake
    case = simulate_tracer_case(TracerTwinConfig(seed=3, n_train=24, n_test=4))
    lengths = case.lengths.clone()
    lengths[7, 1] = lengths[7, 1] * 1000.0 + 5.0
    path = tmp_path / "one_bad.csv"
    write_lengths_csv(path, case.q_train, lengths)
    with pytest.raises(DataError, match="triangle inequality") as info:
        load_tracer_data(path, case.twin.robot)
    assert (info.value.row, info.value.column) == (9, "l2")
