"""The position-measurement file of the data contract (laser tracker points).

Columns: ``q1..qN`` (deg, or rad), ``x, y, z`` (mm, or m) of the TCP/reflector in the
``instrument`` frame, optional ``rx, ry, rz`` (fixed-axis XYZ, deg), optional wrench
``fx, fy, fz, tx, ty, tz`` (N, N*m) and optional ``temp`` (deg C).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchcal.core.errors import DataError
from torchcal.core.hashing import sha256_file
from torchcal.core.io import atomic_write_text
from torchcal.data.csv_table import check_joint_limits, check_units, joint_columns, read_csv_table
from torchcal.data.plausibility import check_joint_unit, check_point_spread
from torchcal.kinematics.robot import RobotModel
from torchcal.kinematics.transforms import euler_xyz_to_matrix

POSITION = ("x", "y", "z")
ORIENTATION = ("rx", "ry", "rz")
WRENCH = ("fx", "fy", "fz", "tx", "ty", "tz")
TEMPERATURE = ("temp",)


@dataclass(frozen=True)
class Measurements:
    """A validated set of poses, SI units, float64.

    Attributes:
        q: ``(n, N)`` commanded joints, rad.
        position: ``(n, 3)`` measured TCP positions, instrument frame, m.
        rotation: ``(n, 3, 3)`` measured tool orientation in the instrument frame, or ``None``.
        wrench: ``(n, 6)`` applied wrench at the tool (N, N*m), or ``None``.
        temperature: ``(n,)`` deg C, or ``None``.
        source: file path, and ``line_numbers`` of each pose in it.
        series: ``(n,)`` long index of the measurement series (file) of each pose when several
            series of one robot are pooled (:mod:`torchcal.data.series`), else ``None``.
    """

    q: torch.Tensor
    position: torch.Tensor
    rotation: torch.Tensor | None = None
    wrench: torch.Tensor | None = None
    temperature: torch.Tensor | None = None
    source: str = "<memory>"
    line_numbers: tuple[int, ...] = field(default_factory=tuple)
    sha256: str = ""
    series: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.q.shape[0])

    def subset(self, index: torch.Tensor | np.ndarray | list[int]) -> Measurements:
        idx = torch.as_tensor(index, dtype=torch.long)

        def pick(t):
            return None if t is None else t[idx]

        lines = tuple(self.line_numbers[i] for i in idx.tolist()) if self.line_numbers else ()
        return Measurements(
            q=self.q[idx], position=self.position[idx], rotation=pick(self.rotation),
            wrench=pick(self.wrench), temperature=pick(self.temperature), source=self.source,
            line_numbers=lines, sha256=self.sha256, series=pick(self.series),
        )

    def to(self, device: str | torch.device) -> Measurements:
        def move(t):
            return None if t is None else t.to(device)

        return Measurements(
            q=self.q.to(device), position=self.position.to(device), rotation=move(self.rotation),
            wrench=move(self.wrench), temperature=move(self.temperature), source=self.source,
            line_numbers=self.line_numbers, sha256=self.sha256, series=self.series,
        )


#: ``temp`` (deg C) outside this range is refused: no robot cell is measured there (a value in kelvin, or a typo).
TEMPERATURE_RANGE_C = (-40.0, 90.0)


#: Joint values closer than this (rad) in every joint are one configuration measured again: an encoder's
#: readback of a repeat differs by ~1e-5 rad, and 1e-3 rad moves a tool 1 m out by 1 mm at most.
SAME_CONFIGURATION_RAD = 1e-3


def count_configurations(q: torch.Tensor) -> int:
    """Distinct joint configurations among the rows ``q (n, N)`` rad (a repeat, within
    :data:`SAME_CONFIGURATION_RAD` per joint, measures the same point again: no new geometry)."""
    if len(q) == 0:
        return 0
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    # rows within the tolerance of each other (max over joints) chain into one configuration; not a
    # rounding grid, whose cell borders would split a repeat whose readbacks straddle one
    points = q.detach().cpu().to(torch.float64).numpy()
    pairs = cKDTree(points).query_pairs(SAME_CONFIGURATION_RAD, p=np.inf, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points), len(points)))
    return int(connected_components(graph, directed=False)[0])


def load_measurements(
    path: str | Path,
    robot: RobotModel,
    *,
    joint_unit: str = "deg",
    length_unit: str = "mm",
    check_limits: bool = True,
    limit_tolerance_deg: float = 0.01,
    check_plausible: bool = True,
) -> Measurements:
    """Read and validate a position-measurement CSV against ``robot``.

    With ``check_plausible`` the file's size is compared with the nominal robot's first
    (:mod:`torchcal.data.plausibility`: joints in radians, points in metres, wild points).

    Raises:
        DataError: naming file, row and column for missing, extra or misnamed columns, empty,
            non-numeric or non-finite cells, joints outside the robot's limits, a joint count
            that does not match the robot, and exactly duplicated rows.
    """
    check_units(joint_unit, length_unit, path)
    table = read_csv_table(path)
    p = str(table.path)
    header = table.header
    n = robot.dof
    expected_q = joint_columns(header, p, n, robot.name)
    allowed = set(expected_q) | set(POSITION) | set(ORIENTATION) | set(WRENCH) | set(TEMPERATURE)
    extra = [h for h in header if h not in allowed]
    if extra:
        hint = ""
        lowered = {h.lower(): h for h in allowed}
        if extra[0].lower().strip() in lowered:
            hint = f" (did you mean '{lowered[extra[0].lower().strip()]}'? names are case-sensitive)"
        raise DataError(
            f"unknown column '{extra[0]}'{hint}; allowed: q1..q{n}, x,y,z, rx,ry,rz, fx..tz, temp",
            path=p, row=1, column=extra[0],
        )
    missing = [c for c in POSITION if c not in header]
    if missing:
        raise DataError(f"missing column(s) {missing}; a position file needs x, y, z", path=p, row=1, column=missing[0])
    present_or = [c for c in ORIENTATION if c in header]
    if present_or and len(present_or) != 3:
        raise DataError(f"orientation needs all of rx, ry, rz; found only {present_or}", path=p, row=1, column=present_or[0])
    present_w = [c for c in WRENCH if c in header]
    if present_w and len(present_w) != 6:
        raise DataError(f"a wrench needs all of {list(WRENCH)}; found only {present_w}", path=p, row=1, column=present_w[0])

    q_deg = np.stack([table.column(c) for c in expected_q], 1)
    q = q_deg * (math.pi / 180.0) if joint_unit == "deg" else q_deg
    scale = 1e-3 if length_unit == "mm" else 1.0
    pos = np.stack([table.column(c) for c in POSITION], 1) * scale

    if check_limits:
        check_joint_limits(q_deg, joint_unit, robot.joint_limits.numpy(), path=p, lines=table.line_numbers,
                           robot_name=robot.name, tolerance_deg=limit_tolerance_deg)
    if check_plausible:
        check_joint_unit(q_deg, joint_unit, robot.joint_limits.numpy(), path=p, lines=table.line_numbers)
        check_point_spread(robot, torch.from_numpy(q), torch.from_numpy(pos), length_unit, path=p,
                           lines=table.line_numbers)

    rotation = None
    if present_or:
        ang = np.stack([table.column(c) for c in ORIENTATION], 1) * (math.pi / 180.0)
        rotation = euler_xyz_to_matrix(torch.from_numpy(ang))
    wrench = torch.from_numpy(np.stack([table.column(c) for c in WRENCH], 1)) if present_w else None
    temperature = None
    if "temp" in header:
        temp = table.column("temp")
        outside = np.flatnonzero((temp < TEMPERATURE_RANGE_C[0]) | (temp > TEMPERATURE_RANGE_C[1]))
        if len(outside):
            k = int(outside[0])
            raise DataError(f"temperature {temp[k]:g} deg C is outside {TEMPERATURE_RANGE_C[0]:g} to "
                            f"{TEMPERATURE_RANGE_C[1]:g} deg C, where robots are measured (temp is in deg C; kelvin read "
                            "233 to 363)",
                            path=p, row=table.line_numbers[k], column="temp")
        temperature = torch.from_numpy(temp)

    # Exactly repeated rows are a copy-paste accident; the same joints measured again with a
    # different result are legitimate repeatability data and are kept.
    raw = np.concatenate([q_deg, pos], 1)
    _, first, counts = np.unique(raw, axis=0, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup_row = raw[first[counts > 1][0]]
        hits = [table.line_numbers[k] for k in range(len(raw)) if np.array_equal(raw[k], dup_row)]
        raise DataError(
            f"duplicates row {hits[0]} exactly (same joints and same measurement); remove the copy",
            path=p, row=hits[1], column="q1",
        )
    _, q_counts = np.unique(q_deg, axis=0, return_counts=True)
    if (q_counts > 1).any():
        warnings.warn(
            f"{p}: {int((q_counts > 1).sum())} joint configuration(s) appear more than once; they are "
            "kept as repeated measurements",
            stacklevel=2,
        )
    digest = sha256_file(p)
    return Measurements(
        q=torch.from_numpy(q), position=torch.from_numpy(pos), rotation=rotation, wrench=wrench,
        temperature=temperature, source=p, line_numbers=tuple(table.line_numbers), sha256=digest,
    )


def write_measurements_csv(
    path: str | Path,
    q: torch.Tensor,
    position: torch.Tensor,
    *,
    extra: dict[str, torch.Tensor] | None = None,
) -> None:
    """Write a contract position file (deg, mm) atomically."""
    cols = [f"q{i}" for i in range(1, q.shape[1] + 1)] + list(POSITION)
    data = [q.detach().cpu().numpy() * (180.0 / math.pi), position.detach().cpu().numpy() * 1e3]
    for name, values in (extra or {}).items():
        cols.append(name)
        data.append(values.detach().cpu().numpy().reshape(-1, 1))
    arr = np.concatenate(data, 1)
    lines = [",".join(cols)] + [",".join(f"{v:.10f}" for v in row) for row in arr]
    atomic_write_text(path, "\n".join(lines) + "\n")
