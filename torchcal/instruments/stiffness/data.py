"""Loader of the stiffness measurement file (data contract) -> validated SI tensors.

Columns (header row, one loaded pose per row):

=====================  ==========================================================  =========
``q1..qN``             commanded joints                                            deg (rad)
``fx, fy, fz``         force applied at the TCP, ``tool`` frame                   N
``tx, ty, tz``         moment about the TCP, ``tool`` frame                       N m
``dx, dy, dz``         loaded minus unloaded TCP position, ``instrument`` frame   mm
``drx, dry, drz``      optional: loaded-from-unloaded rotation vector, instrument  deg
``x, y, z``            optional: unloaded TCP position, ``instrument`` frame       mm
=====================  ==========================================================  =========

Without ``x, y, z`` the instrument frame is the robot ``base`` frame. Every problem raises a
:class:`~torchcal.core.errors.DataError` naming the file, the line (the header is line 1) and the
column.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from torchcal.core.errors import DataError
from torchcal.data.csv_table import check_units, joint_columns, read_csv_table
from torchcal.stiffness.experiment import StiffnessData

WRENCH_COLUMNS = ("fx", "fy", "fz", "tx", "ty", "tz")
DEFLECTION_COLUMNS = ("dx", "dy", "dz")
ROTATION_COLUMNS = ("drx", "dry", "drz")
POSITION_COLUMNS = ("x", "y", "z")


def _group(header: tuple[str, ...], names: tuple[str, ...], path: str, what: str, required: bool) -> bool:
    present = [c for c in names if c in header]
    missing = [c for c in names if c not in header]
    if required and missing:
        raise DataError(f"missing column(s) {missing}; a stiffness file needs {what}", path=path, row=1, column=missing[0])
    if present and missing:
        raise DataError(f"{what} needs all of {list(names)}; found only {present}", path=path, row=1, column=missing[0])
    return not missing


def load_stiffness(
    path: str | Path,
    *,
    n_joints: int | None = None,
    joint_unit: str = "deg",
    length_unit: str = "mm",
    device: str | torch.device = "cpu",
) -> StiffnessData:
    """Read and validate a stiffness file of the data contract.

    Args:
        path: CSV file.
        n_joints: expected number of joints (the robot's); ``None`` accepts any.
        joint_unit: ``"deg"`` (contract default) or ``"rad"`` for ``q*``.
        length_unit: ``"mm"`` (contract default) or ``"m"`` for ``d*`` and ``x, y, z``.
        device: where the tensors are created.

    Raises:
        DataError: file, line and column of the first problem found.
    """
    path = Path(path)
    p = str(path)
    check_units(joint_unit, length_unit, path)
    table = read_csv_table(path)
    header, rows, lines = table.header, table.rows, list(table.line_numbers)
    joints = joint_columns(header, p, n_joints)
    _group(header, WRENCH_COLUMNS, p, "a wrench", required=True)
    _group(header, DEFLECTION_COLUMNS, p, "a deflection", required=True)
    has_rot = _group(header, ROTATION_COLUMNS, p, "a rotation", required=False)
    has_pos = _group(header, POSITION_COLUMNS, p, "an unloaded position", required=False)
    allowed = set(joints) | set(WRENCH_COLUMNS) | set(DEFLECTION_COLUMNS) | set(ROTATION_COLUMNS) | set(POSITION_COLUMNS)
    extra = [h for h in header if h not in allowed]
    if extra:
        raise DataError(
            f"unknown column '{extra[0]}'; allowed: q1..qN, fx,fy,fz,tx,ty,tz, dx,dy,dz, drx,dry,drz, x,y,z",
            path=p,
            row=1,
            column=extra[0],
        )

    def column(name: str) -> torch.Tensor:
        idx = header.index(name)
        values = []
        for row, line in zip(rows, lines):
            cell = row[idx].strip()
            if cell == "":
                raise DataError("empty cell", path=p, row=line, column=name)
            try:
                value = float(cell)
            except ValueError:
                raise DataError(f"'{cell}' is not a number", path=p, row=line, column=name) from None
            if not math.isfinite(value):
                raise DataError(f"'{cell}' is not a finite number", path=p, row=line, column=name)
            values.append(value)
        return torch.tensor(values, dtype=torch.float64, device=device)

    def block(names) -> torch.Tensor:
        return torch.stack([column(c) for c in names], -1)

    angle = math.pi / 180.0 if joint_unit == "deg" else 1.0
    length = 1e-3 if length_unit == "mm" else 1.0
    wrench = block(WRENCH_COLUMNS)
    zero = (wrench == 0).all(-1).nonzero()
    if zero.numel():
        raise DataError("wrench is zero: a stiffness row needs a load", path=p, row=lines[int(zero[0])], column="fx")
    return StiffnessData(
        q=block(joints) * angle,
        wrench=wrench,
        deflection=block(DEFLECTION_COLUMNS) * length,
        rotation=block(ROTATION_COLUMNS) * (math.pi / 180.0) if has_rot else None,
        unloaded=block(POSITION_COLUMNS) * length if has_pos else None,
        path=p,
    )
