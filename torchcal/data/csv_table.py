"""Strict CSV reading shared by every measurement loader.

Every problem is reported as a :class:`~torchcal.core.errors.DataError` naming the file, the 1-based
line number as a spreadsheet shows it (the header is line 1) and the column.
"""

from __future__ import annotations

import csv
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchcal.core.errors import DataError


@dataclass(frozen=True)
class CsvTable:
    """Header and raw string cells of a CSV file with one record per row."""

    path: Path
    header: tuple[str, ...]
    rows: list[list[str]]
    line_numbers: list[int]

    def column(self, name: str, *, allow_empty: bool = False) -> np.ndarray:
        """Column ``name`` as float64; empty cells become NaN only when ``allow_empty``."""
        idx = self.header.index(name)
        out = np.empty(len(self.rows), dtype=np.float64)
        for k, (row, line) in enumerate(zip(self.rows, self.line_numbers)):
            cell = row[idx].strip()
            if cell == "":
                if allow_empty:
                    out[k] = math.nan
                    continue
                raise DataError("empty cell", path=str(self.path), row=line, column=name)
            try:
                if "_" in cell:  # Python reads '1_0' as 10; no spreadsheet writes it
                    raise ValueError(cell)
                value = float(cell)
            except ValueError:
                raise DataError(f"'{cell}' is not a number", path=str(self.path), row=line, column=name) from None
            if not math.isfinite(value):
                raise DataError(f"'{cell}' is not a finite number", path=str(self.path), row=line, column=name)
            out[k] = value
        return out


#: The most data rows and columns a measurement file may have (memory stays bounded; real files
#: have hundreds to a few thousand poses and tens of columns).
MAX_ROWS = 500_000
MAX_COLUMNS = 1000


def read_csv_table(path: str | Path) -> CsvTable:
    """Read a comma-separated file with a header row; blank lines are skipped."""
    path = Path(path)
    if not path.is_file():
        raise DataError("file not found", path=str(path))
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise DataError("not a UTF-8 text file", path=str(path)) from None
    if "\x00" in text:
        raise DataError("not a text file (holds NUL bytes)", path=str(path))
    n_lines = text.count("\n") + 1
    if n_lines > MAX_ROWS + 1:
        raise DataError(f"has {n_lines} lines; torchcal reads at most {MAX_ROWS} poses per file (a calibration uses "
                        "hundreds to a few thousand): subsample or split the file", path=str(path))
    reader = csv.reader(text.splitlines())
    header: tuple[str, ...] | None = None
    rows: list[list[str]] = []
    lines: list[int] = []
    for line_no, row in enumerate(_records(reader, path), start=1):
        if not row or all(not c.strip() for c in row):
            continue
        if header is None:
            header = tuple(c.strip() for c in row)
            if len(header) > MAX_COLUMNS:
                raise DataError(f"header has {len(header)} columns; a measurement file has tens (at most "
                                f"{MAX_COLUMNS}): is this the right file?", path=str(path), row=line_no)
            if any(not h for h in header):
                raise DataError("header has an empty column name", path=str(path), row=line_no)
            dupes = sorted(h for h, n in Counter(header).items() if n > 1)
            if dupes:
                raise DataError(f"header repeats column(s) {dupes}", path=str(path), row=line_no, column=dupes[0])
            continue
        if len(row) != len(header):
            raise DataError(
                f"has {len(row)} cells but the header has {len(header)}", path=str(path), row=line_no
            )
        rows.append(row)
        lines.append(line_no)
    if header is None:
        raise DataError("file is empty (no header row)", path=str(path))
    if not rows:
        raise DataError("has a header but no data rows", path=str(path))
    return CsvTable(path=path, header=header, rows=rows, line_numbers=lines)


def _records(reader, path: Path):
    """The records of a ``csv.reader``; a malformed one (a field over the size limit...) is a DataError."""
    while True:
        try:
            yield next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            raise DataError(f"unreadable CSV record ({exc})", path=str(path), row=reader.line_num) from None


def check_units(joint_unit: str, length_unit: str, path: str | Path) -> None:
    """Refuse unit names other than those of the data contract (``deg``/``rad``, ``mm``/``m``)."""
    if joint_unit not in ("deg", "rad"):
        raise DataError(f"joint_unit must be 'deg' or 'rad', got {joint_unit!r}", path=str(path))
    if length_unit not in ("mm", "m"):
        raise DataError(f"length_unit must be 'mm' or 'm', got {length_unit!r}", path=str(path))


def joint_columns(header: tuple[str, ...], path: str | Path, n_joints: int | None = None,
                  robot_name: str | None = None) -> list[str]:
    """The joint columns ``q1..qN`` of a header, in order, checked against the robot's joint count.

    With ``robot_name`` every mismatch is reported as what that robot needs; without it, gaps and
    a missing ``q1..qN`` are reported as such and the count is checked when ``n_joints`` is given.
    """
    p = str(path)
    names = [h for h in header if len(h) > 1 and h[0] == "q" and h[1:].isdigit()]
    numbers = sorted(int(h[1:]) for h in names)
    if robot_name is not None and n_joints is not None:
        expected = [f"q{i}" for i in range(1, n_joints + 1)]
        if len(names) != n_joints or set(names) != set(expected):
            raise DataError(f"robot '{robot_name}' has {n_joints} joints, so the file needs columns "
                            f"{expected[0]}..{expected[-1]}; found {names or 'none'}", path=p, row=1)
        return expected
    if not numbers:
        raise DataError("no joint columns q1..qN", path=p, row=1)
    if numbers != list(range(1, len(numbers) + 1)):
        raise DataError(f"joint columns must be q1..qN without gaps, found {names}", path=p, row=1)
    if n_joints is not None and len(numbers) != n_joints:
        raise DataError(f"has {len(numbers)} joint columns but the robot has {n_joints} joints", path=p, row=1)
    return [f"q{i}" for i in numbers]


def read_header(path: str | Path) -> list[str]:
    """The column names (stripped, lower case) of the first non-empty row of the CSV at ``path``.

    Raises:
        DataError: the file is missing or has no header row.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError("file not found", path=str(path))
    try:
        with path.open(encoding="utf-8-sig", newline="") as handle:
            reader = csv.reader(handle)
            for row in _records(reader, path):
                if any(cell.strip() for cell in row):
                    if any("\x00" in cell for cell in row):
                        raise DataError("not a text file (holds NUL bytes)", path=str(path), row=reader.line_num)
                    return [cell.strip().lower() for cell in row]
    except UnicodeDecodeError as exc:
        raise DataError(f"not a UTF-8 text file (byte {exc.start})", path=str(path)) from None
    raise DataError("the file is empty (no header row)", path=str(path))


def check_joint_limits(
    q_file: np.ndarray,
    joint_unit: str,
    limits_rad: np.ndarray,
    *,
    path: str | Path,
    lines: list[int] | tuple[int, ...],
    columns: list[str] | None = None,
    robot_name: str | None = None,
    tolerance_deg: float = 0.01,
) -> None:
    """Refuse the first joint value outside the robot's limits, in the file's own unit.

    Args:
        q_file: ``(B, N)`` joints as written in the file (``joint_unit``: ``deg`` or ``rad``).
        limits_rad: ``(N, 2)`` lower and upper limits, rad; ``-inf, inf`` for a continuous joint,
            which no value is outside.
        lines: file line of each row; ``columns`` the name of each joint column (``q1..qN``).
        tolerance_deg: how far outside a limit a value may be (rounding in files), deg.

    Raises:
        DataError: value, limits (file unit), file, line and column of the first violation.
    """
    to_rad = math.pi / 180.0 if joint_unit == "deg" else 1.0
    tol = math.radians(tolerance_deg)
    q = q_file * to_rad
    bad = (q < limits_rad[:, 0] - tol) | (q > limits_rad[:, 1] + tol)
    if not bad.any():
        return
    k, j = map(int, np.argwhere(bad)[0])
    f = 1.0 / to_rad
    of_robot = f" of robot '{robot_name}'" if robot_name else ""
    raise DataError(
        f"{q_file[k, j]:g} {joint_unit} is outside joint {j + 1}'s limits "
        f"[{limits_rad[j, 0] * f:g}, {limits_rad[j, 1] * f:g}] {joint_unit}{of_robot}",
        path=str(path), row=lines[k], column=(columns or [f"q{i + 1}" for i in range(q.shape[1])])[j],
    )
