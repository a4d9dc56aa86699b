"""Loading a single-station length file: ``q1..qN, l1`` (deg and mm unless told otherwise)."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import torch

from torchcal.core.errors import DataError
from torchcal.data.csv_table import check_units, joint_columns, read_csv_table
from torchcal.data.measurements import count_configurations
from torchcal.data.plausibility import check_joint_unit
from torchcal.instruments.tracer.data import TracerData, check_length_spread, station_columns
from torchcal.kinematics.robot import RobotModel

#: Distinct joint configurations a fit needs: anchor (3), offset (1) and attachment (3) are 7
#: unknowns, and the structures are compared by cross-validation, whose training folds need them
#: with some to spare.
FIT_MIN_CONFIGURATIONS = 20
FIT_PURPOSE = "a length-station fit (anchor, attachment, offset: 7 unknowns, and cross-validation)"
#: Distinct joint configurations ``evaluate`` needs to re-fit anchor and offset (4 unknowns): with five
#: the re-fit put a real anchor 120 mm off and scored 0.16 mm where the model misses by 2.8 mm.
REFIT_MIN_CONFIGURATIONS = 10
REFIT_PURPOSE = ("evaluate to re-fit anchor and offset (4 unknowns, checked on the rest; refit_anchor=false "
                 "keeps the fitted ones)")
def is_single_station(header: set[str]) -> bool:
    """True for a header with ``l1`` and no ``l2``: one length station (this package), not a tracer."""
    return "l1" in header and "l2" not in header


def check_configurations(data: TracerData, minimum: int, purpose: str) -> None:
    """Refuse ``data`` with fewer than ``minimum`` distinct joint configurations for ``purpose``.

    Raises:
        DataError: naming the file, the count of configurations and rows, and what needs them.
    """
    n = count_configurations(data.q)
    if n >= minimum:
        return
    repeats = (f" in {len(data)} rows (rows that repeat a joint configuration measure the same point again: "
               "repeatability data, not calibration data)" if n < len(data) else "")
    raise DataError(f"{n} distinct joint configuration(s){repeats} are too few for {purpose}, which needs at least "
                    f"{minimum}", path=data.source)


def load_length_data(path: str | Path, robot: RobotModel, *, joint_unit: str = "deg", length_unit: str = "mm",
                     check_limits: bool = True, min_configurations: int = FIT_MIN_CONFIGURATIONS,
                     purpose: str = FIT_PURPOSE) -> TracerData:
    """Read ``q1..qN, l1`` into a one-station :class:`~torchcal.instruments.tracer.data.TracerData` (SI).

    Every problem is a :class:`DataError` naming the file, row and column; rows stay in file
    order (the order the blocked cross-validation relies on). Refused besides the cells: another
    station column without ``l2`` (``l1, l3``: a gap, not one station), joints that look like
    radians read as degrees, fewer than ``min_configurations`` distinct joint configurations
    (repeated rows add none; ``purpose`` says in the message what needs them), a constant length
    column (a stuck sensor) and readings whose range does not fit the nominal TCP's motion
    (lengths in the wrong unit).

    Args:
        min_configurations: distinct joint configurations required (:data:`FIT_MIN_CONFIGURATIONS`
            for a fit, :data:`REFIT_MIN_CONFIGURATIONS` for ``evaluate`` re-fitting anchor and offset).
        purpose: what needs them, for the message.
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
    q_file = np.stack([table.column(j) for j in joints], -1)
    check_joint_unit(q_file, joint_unit, robot.joint_limits.numpy(), path=str(path), lines=table.line_numbers)
    scale = math.pi / 180.0 if joint_unit == "deg" else 1.0
    q = torch.tensor(q_file * scale, dtype=torch.float64)
    lengths = torch.tensor(table.column("l1") * (1e-3 if length_unit == "mm" else 1.0), dtype=torch.float64)
    if check_limits:
        lim = robot.joint_limits
        outside = (q < lim[:, 0] - 1e-6) | (q > lim[:, 1] + 1e-6)
        if bool(outside.any()):
            i, j = (int(v) for v in outside.nonzero()[0])
            raise DataError(f"{float(q[i, j]) / scale:.4g} {joint_unit} is outside the joint limits of {robot.name} "
                            "(check_limits=false accepts it)", path=str(path), row=table.line_numbers[i], column=joints[j])
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    data = TracerData(q, lengths.unsqueeze(-1), str(path), tuple(table.line_numbers), digest)
    check_configurations(data, min_configurations, purpose)
    check_length_spread(data, robot, length_unit)
    return data
