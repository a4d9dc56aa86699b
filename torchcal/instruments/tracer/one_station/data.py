"""Loading a single-station length file: ``q1..qN, l1`` (deg and mm unless told otherwise)."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import torch

from torchcal.core.errors import DataError
from torchcal.data.csv_table import check_units, joint_columns, read_csv_table
from torchcal.instruments.tracer.data import TracerData, check_length_spread, station_columns
from torchcal.kinematics.robot import RobotModel


def is_single_station(header: set[str]) -> bool:
    """True for a header with ``l1`` and no ``l2``: one length station (this package), not a tracer."""
    return "l1" in header and "l2" not in header


def load_length_data(path: str | Path, robot: RobotModel, *, joint_unit: str = "deg", length_unit: str = "mm",
                     check_limits: bool = True) -> TracerData:
    """Read ``q1..qN, l1`` into a one-station :class:`~torchcal.instruments.tracer.data.TracerData` (SI).

    Every problem is a :class:`DataError` naming the file, row and column; rows stay in file
    order (the order the blocked cross-validation relies on). Refused besides the cells: another
    station column without ``l2`` (``l1, l3``: a gap, not one station), and readings whose range
    does not fit the nominal TCP's motion (lengths in the wrong unit).
    """
    path = Path(path)
    check_units(joint_unit, length_unit, path)
    table = read_csv_table(path)
    header = tuple(h.lower() for h in table.header)
    table = type(table)(path=table.path, header=header, rows=table.rows, line_numbers=table.line_numbers)
    if "l1" not in header:
        raise DataError("missing column 'l1' (a length-station file has q1..qN, l1)", path=str(path), row=1)
    # 'l1, l3' is recognised here (no l2) but is a tracer file with a gap, not one station
    station_columns(header, str(path))
    joints = joint_columns(header, path, robot.dof, robot.name)
    scale = math.pi / 180.0 if joint_unit == "deg" else 1.0
    q = torch.tensor(np.stack([table.column(j) for j in joints], -1) * scale, dtype=torch.float64)
    lengths = torch.tensor(table.column("l1") * (1e-3 if length_unit == "mm" else 1.0), dtype=torch.float64)
    if check_limits:
        lim = robot.joint_limits
        outside = (q < lim[:, 0] - 1e-6) | (q > lim[:, 1] + 1e-6)
        if bool(outside.any()):
            i, j = (int(v) for v in outside.nonzero()[0])
            raise DataError(f"{float(q[i, j]) / scale:.4g} {joint_unit} is outside the joint limits of {robot.name} "
                            "(check_limits=false accepts it)", path=str(path), row=table.line_numbers[i], column=joints[j])
    if len(q) < 20:
        raise DataError(f"{len(q)} rows are too few for a length station (anchor, attachment, offset: 7 unknowns "
                        "and cross-validation)", path=str(path))
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    data = TracerData(q, lengths.unsqueeze(-1), str(path), tuple(table.line_numbers), digest)
    check_length_spread(data, robot, length_unit)
    return data
