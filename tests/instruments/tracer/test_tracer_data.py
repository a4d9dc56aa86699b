"""The tracer length file: units, missing lengths, and clear errors for files that cannot be solved."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from torchcal.core.errors import DataError
from torchcal.instruments.tracer.data import load_tracer_data
from torchcal.instruments.tracer.twin_case import (
    TracerTwinConfig,
    simulate_tracer_case,
    write_lengths_csv,
)


@pytest.fixture(scope="module")
def case():
    return simulate_tracer_case(TracerTwinConfig(seed=3, n_train=24, n_test=4))


def _write(path, q_deg, lengths_mm, header=None):
    cols = header or [f"q{i}" for i in range(1, q_deg.shape[1] + 1)] + [f"l{j}" for j in range(1, lengths_mm.shape[1] + 1)]
    lines = [",".join(cols)]
    for qi, li in zip(q_deg.tolist(), lengths_mm.tolist()):
        lines.append(",".join([f"{v:.10f}" for v in qi] + ["" if math.isnan(v) else f"{v:.12f}" for v in li]))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_units_and_missing_lengths_round_trip(tmp_path, case):
    lengths = case.lengths.clone()
    lengths[2, 1] = lengths[5, 3] = torch.nan
    path = tmp_path / "lengths.csv"
    write_lengths_csv(path, case.q_train, lengths)
    data = load_tracer_data(path, case.twin.robot)
    assert data.lengths.shape == (24, 4) and data.line(0) == 2
    assert torch.isnan(data.lengths[2, 1]) and torch.isnan(data.lengths[5, 3]) and int(data.seen.sum()) == 94
    torch.testing.assert_close(data.q, case.q_train, atol=1e-12, rtol=0)
    torch.testing.assert_close(data.lengths.nan_to_num(), lengths.nan_to_num(), atol=1e-9, rtol=0)
    # the same numbers in rad and m give the same tensors
    other = _write(tmp_path / "si.csv", case.q_train, lengths)
    si = load_tracer_data(other, case.twin.robot, joint_unit="rad", length_unit="m")
    torch.testing.assert_close(si.q, data.q, atol=1e-9, rtol=0)
    torch.testing.assert_close(si.lengths.nan_to_num(), data.lengths.nan_to_num(), atol=1e-9, rtol=0)


def test_blind_pose_is_dropped_with_a_warning(tmp_path, case):
    lengths = case.lengths * 1e3
    lengths[4] = torch.nan
    path = _write(tmp_path / "blind.csv", case.q_train * 180 / math.pi, lengths)
    with pytest.warns(UserWarning, match="seen by no station"):
        data = load_tracer_data(path, case.twin.robot)
    assert len(data) == 23 and 6 not in data.line_numbers


@pytest.mark.parametrize(
    "edit, pattern",
    [
        (lambda q, l: (q, l[:, :3]), r"3 station column\(s\).*at least 4 stations"),
        (lambda q, l: (q[:10], l[:10]), r"row|lengths of 10 pose\(s\).*cannot determine"),
        (lambda q, l: (q, _blank(l, slice(3, None), 2)), r"column 'l3': station 3 saw only 3 pose\(s\)"),
        (lambda q, l: (q, _scale(l, 7, 1, 1000.0)), r"row 9, column 'l2': station 2's reading changes by .*triangle"),
    ],
)
def test_unsolvable_or_inconsistent_files_name_row_and_column(tmp_path, case, edit, pattern):
    q, lengths = edit(case.q_train * 180 / math.pi, case.lengths * 1e3)
    path = _write(tmp_path / "bad.csv", q, lengths)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(DataError, match=pattern):
            load_tracer_data(path, case.twin.robot)


def _blank(lengths, rows, col):
    lengths = lengths.clone()
    lengths[rows, col] = torch.nan
    return lengths


def _scale(lengths, row, col, factor):
    lengths = lengths.clone()
    lengths[row, col] = lengths[row, col] * factor + 5000.0
    return lengths


def test_count_rule_is_the_unknowns_less_the_frame(tmp_path, case):
    # 4 stations, n poses seen by all: 4n >= 3n + 16 - 6 + 1 needs n >= 11
    q, lengths = case.q_train * 180 / math.pi, case.lengths * 1e3
    ok = load_tracer_data(_write(tmp_path / "ok.csv", q[:11], lengths[:11]), case.twin.robot)
    assert len(ok) == 11
    with pytest.raises(DataError, match=r"44 lengths|40 lengths"):
        load_tracer_data(_write(tmp_path / "few.csv", q[:10], lengths[:10]), case.twin.robot)


def test_millimetres_read_as_metres_name_the_unit(tmp_path, case):
    # refused by the readings' spread before the triangle inequality, so the message names the unit
    path = tmp_path / "lengths.csv"
    write_lengths_csv(path, case.q_train, case.lengths)
    with pytest.raises(DataError, match=r"column 'l\d': .*ratio .*: the lengths look like millimetres; set length_unit=mm"):
        load_tracer_data(path, case.twin.robot, length_unit="m")


@pytest.mark.parametrize(
    "header_edit, pattern",
    [
        (lambda h: h[:5] + h[6:], r"needs columns q1..q6"),
        (lambda h: h[:7] + ["l3", "l4", "l5"], r"l1..lM without gaps"),
        (lambda h: h[:9] + ["L4"], r"unknown column 'L4'.*did you mean 'l4'"),
    ],
)
def test_header_errors(tmp_path, case, header_edit, pattern):
    header = [f"q{i}" for i in range(1, 7)] + ["l1", "l2", "l3", "l4"]
    new = header_edit(header)
    path = tmp_path / "h.csv"
    path.write_text(",".join(new) + "\n" + ",".join("1" for _ in new) + "\n")
    with pytest.raises(DataError, match=pattern):
        load_tracer_data(path, case.twin.robot)


def test_bad_cell_names_row_and_column(tmp_path, case):
    path = tmp_path / "lengths.csv"
    write_lengths_csv(path, case.q_train, case.lengths)
    lines = path.read_text().splitlines()
    cells = lines[3].split(",")
    cells[8] = "abc"
    lines[3] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"row 4, column 'l3': 'abc' is not a number"):
        load_tracer_data(path, case.twin.robot)
