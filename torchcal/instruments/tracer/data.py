"""The laser-tracer length file of the data contract -> validated SI tensors.

Columns (header row, one robot pose per row):

=============  ===============================================================  =========
``q1..qN``     commanded joints                                                 deg (rad)
``l1..lM``     interferometric length from station ``j`` to the reflector,      mm (m)
               relative to that station's unknown dead path; empty where the
               station did not see the pose
=============  ===============================================================  =========

Checks, each a :class:`~torchcal.core.errors.DataError` naming file, line (the header is line 1) and
column: the strict CSV rules of :mod:`torchcal.data.csv_table`, the joint count of the robot, the
joint limits, station columns ``l1..lM`` without gaps, at least four stations, every station seeing
enough poses, enough lengths for the unknowns (``K >= 3n + 4m - 6 + 1`` over the poses seen by at
least three stations: points, stations and dead paths less the six of a rigid motion, plus one
for the residual variance), the size of the readings against the nominal robot (lengths in the
wrong unit), and the triangle inequality against the nominal robot: between two poses a
station's reading can change by no more than the reflector moved.
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
from torchcal.data.csv_table import check_joint_limits, check_units, joint_columns, read_csv_table
from torchcal.data.plausibility import distances_from_median, length_unit_hint
from torchcal.instruments.tracer.locate import MIN_STATIONS_PER_POSE
from torchcal.kinematics.robot import RobotModel

MIN_STATIONS = 4
MIN_POSES_PER_STATION = 5  # position and dead path (4 unknowns) plus one to check them
#: Widest spread of one station's readings / the nominal TCP's spread outside this range is refused
#: as a unit mistake (metres read as mm give about 1e-3, mm read as metres about 1e3).
LENGTH_SPREAD_RATIO_RANGE = (0.01, 100.0)


@dataclass(frozen=True)
class TracerData:
    """A validated tracer session, SI units, float64.

    Attributes:
        q: ``(n, N)`` commanded joints, rad.
        lengths: ``(n, m)`` readings ``l_ij``, m, NaN where station ``j`` did not see pose ``i``.
        source: file path; ``line_numbers`` the line of every pose in it; ``sha256`` its hash.
    """

    q: torch.Tensor
    lengths: torch.Tensor
    source: str = "<memory>"
    line_numbers: tuple[int, ...] = field(default_factory=tuple)
    sha256: str = ""

    def __len__(self) -> int:
        return int(self.q.shape[0])

    @property
    def n_stations(self) -> int:
        return int(self.lengths.shape[1])

    @property
    def seen(self) -> torch.Tensor:
        """``(n, m)`` bool: which lengths were measured."""
        return torch.isfinite(self.lengths)

    def line(self, i: int) -> int | None:
        """File line of pose ``i`` (``None`` for in-memory data)."""
        return self.line_numbers[i] if self.line_numbers else None

    def subset(self, index: torch.Tensor | list[int]) -> TracerData:
        idx = torch.as_tensor(index, dtype=torch.long)
        lines = tuple(self.line_numbers[i] for i in idx.tolist()) if self.line_numbers else ()
        return TracerData(self.q[idx], self.lengths[idx], self.source, lines, self.sha256)

    def to(self, device: str | torch.device) -> TracerData:
        return TracerData(self.q.to(device), self.lengths.to(device), self.source, self.line_numbers, self.sha256)


def station_columns(header: tuple[str, ...], path: str) -> list[str]:
    """The station columns ``l1..lM`` of ``header`` in station order.

    Raises:
        DataError: a station number is missing (``l1, l3``) or repeated (``l1, l01``); names the
            first column past the gap.
    """
    names = [h for h in header if len(h) > 1 and h[0] == "l" and h[1:].isdigit()]
    numbers = sorted(int(h[1:]) for h in names)
    if numbers != list(range(1, len(numbers) + 1)):
        missing = next(k for k in range(1, len(numbers) + 2) if k not in numbers)
        past = [h for h in names if int(h[1:]) > missing]
        if past:  # a gap: name the first column after it
            column = min(past, key=lambda h: int(h[1:]))
            why = f"'{column}' without 'l{missing}'"
        else:  # no gap, so a number is written twice ('l1' and 'l01')
            column = next(h for h in names if numbers.count(int(h[1:])) > 1)
            why = f"station {int(column[1:])} appears twice"
        raise DataError(f"station columns must be l1..lM without gaps, found {names}: {why}",
                        path=path, row=1, column=column)
    return [f"l{i}" for i in numbers]


def _check_station_count(names: list[str], path: str) -> None:
    if len(names) < MIN_STATIONS:
        raise DataError(
            f"{len(names)} station column(s) {names}: self-calibrating multilateration needs at least "
            f"{MIN_STATIONS} stations (l1..l{MIN_STATIONS})",
            path=path, row=1,
        )


def load_tracer_data(
    path: str | Path,
    robot: RobotModel,
    *,
    joint_unit: str = "deg",
    length_unit: str = "mm",
    check_limits: bool = True,
    limit_tolerance_deg: float = 0.01,
    triangle_tolerance_mm: float = 20.0,
) -> TracerData:
    """Read and validate a tracer length file against ``robot``.

    Poses that no station saw are dropped with a warning (they carry nothing). Poses seen by one
    or two stations are kept: the joint method uses them, the two-step method cannot locate them.

    Args:
        path: CSV file.
        robot: the nominal robot (joint count, limits, and nominal TCP for the triangle check).
        joint_unit: ``"deg"`` (contract default) or ``"rad"``.
        length_unit: ``"mm"`` (contract default) or ``"m"``.
        check_limits: reject joints outside the robot's limits (plus ``limit_tolerance_deg``).
        triangle_tolerance_mm: how much a reading's change between two poses may exceed the
            nominal TCP displacement (nominal kinematics are off by a few mm) before the length
            is called inconsistent.

    Raises:
        DataError: file, line and column of the first problem found.
    """
    check_units(joint_unit, length_unit, path)
    table = read_csv_table(path)
    p = str(table.path)
    header = table.header
    n_j = robot.dof
    expected_q = joint_columns(header, p, n_j, robot.name)
    stations = station_columns(header, p)
    extra = [h for h in header if h not in set(expected_q) | set(stations)]
    if extra:
        hint = ""
        lowered = extra[0].strip().lower()
        if lowered in set(expected_q) or (lowered[:1] == "l" and lowered[1:].isdigit()):
            hint = f" (did you mean '{lowered}'? names are case-sensitive)"
        raise DataError(f"unknown column '{extra[0]}'{hint}; a tracer file has q1..q{n_j}, l1..lM", path=p, row=1, column=extra[0])
    _check_station_count(stations, p)

    q_user = np.stack([table.column(c) for c in expected_q], 1)
    q = q_user * (math.pi / 180.0) if joint_unit == "deg" else q_user
    scale = 1e-3 if length_unit == "mm" else 1.0
    lengths = np.stack([table.column(c, allow_empty=True) for c in stations], 1) * scale
    lines = list(table.line_numbers)

    if check_limits:
        check_joint_limits(q_user, joint_unit, robot.joint_limits.numpy(), path=p, lines=lines,
                           robot_name=robot.name, tolerance_deg=limit_tolerance_deg)
    raw = np.where(np.isfinite(lengths), lengths, -1e300)
    _, first, counts = np.unique(np.concatenate([q_user, raw], 1), axis=0, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup = np.concatenate([q_user, raw], 1)[first[counts > 1][0]]
        hits = [lines[k] for k in range(len(lines)) if np.array_equal(np.concatenate([q_user[k], raw[k]]), dup)]
        raise DataError(
            f"duplicates row {hits[0]} exactly (same joints and same lengths); remove the copy", path=p, row=hits[1], column="q1"
        )

    blind = ~np.isfinite(lengths).any(1)
    if blind.any():
        warnings.warn(
            f"{p}: {int(blind.sum())} pose(s) seen by no station (first at row {lines[int(np.argmax(blind))]}) are ignored",
            stacklevel=2,
        )
        keep = ~blind
        q, q_user, lengths = q[keep], q_user[keep], lengths[keep]
        lines = [lines[i] for i in np.flatnonzero(keep)]
    data = TracerData(
        q=torch.from_numpy(q), lengths=torch.from_numpy(lengths), source=p, line_numbers=tuple(lines),
        sha256=sha256_file(p),
    )
    check_solvable(data)
    # before the triangle inequality: a whole file in the wrong unit deserves the unit's name
    check_length_spread(data, robot, length_unit)
    check_triangle_inequality(data, robot, tolerance_m=triangle_tolerance_mm * 1e-3)
    return data


def check_length_spread(data: TracerData, robot: RobotModel, length_unit: str) -> None:
    """Refuse readings whose size does not match the nominal TCP's motion at the file's joints.

    A station's reading changes between two poses by at most the reflector's displacement and,
    seen from a station beside the workspace, by a good part of it; so the spread of a station's
    readings is comparable with the nominal TCP's. Lengths written in metres but read as mm (or the
    reverse) miss it by about 1000, which the fit would absorb into a robot 1000 times too small
    (or large). Dead paths make the readings' absolute values arbitrary, hence spreads (median
    distance from the median, as for tracker points: a single wrong reading is left to the
    triangle inequality, which names its row), not values.

    A column that reads the same value at most of its poses (median distance 0) while the robot
    moves is no unit mistake but a sensor that reads no change (stuck or disconnected); it is
    refused as such, whatever the unit.

    Args:
        data: readings ``(n, m)`` in m as read (NaN where not seen) and joints, rad.
        robot: the nominal robot.
        length_unit: the unit the file was read in (``mm`` or ``m``), for the message.

    Raises:
        DataError: naming the file and the station column: a constant column, or the widest
            spread and the likely unit.
    """
    if len(data) < MIN_POSES_PER_STATION:
        return
    with torch.no_grad():
        tcp = robot.tcp_position(data.q.to(torch.float64)).cpu().numpy()
    reference = float(np.median(distances_from_median(tcp)))
    if reference <= 1e-4:  # the robot hardly moved: nothing to compare with
        return
    lengths = data.lengths.cpu().numpy()
    spread = np.zeros(lengths.shape[1])
    for j in range(lengths.shape[1]):
        col = lengths[np.isfinite(lengths[:, j]), j]
        if col.size:
            spread[j] = float(np.median(np.abs(col - np.median(col))))
        if col.size >= MIN_POSES_PER_STATION and spread[j] == 0.0:
            value = float(np.median(col)) * (1e3 if length_unit == "mm" else 1.0)
            if float(np.ptp(col)) == 0.0:
                what = f"every one of its {col.size} readings is {value:.6g} {length_unit}: the column is constant"
            else:
                share = int((col == np.median(col)).sum())
                what = f"{share} of its {col.size} readings are {value:.6g} {length_unit}: the column is mostly constant"
            raise DataError(
                f"{what} while the nominal robot's TCP moves {reference * 1e3:.4g} mm around its median at the same "
                "joints: the sensor reads no change (a stuck or disconnected sensor), whatever the length unit",
                path=data.source, column=f"l{j + 1}",
            )
    j = int(spread.argmax())
    ratio = float(spread[j]) / reference
    low, high = LENGTH_SPREAD_RATIO_RANGE
    if low <= ratio <= high:
        return
    hint = length_unit_hint(ratio, length_unit, "lengths", robot.name)
    widest = "" if data.n_stations == 1 else " (the widest of any station)"
    raise DataError(
        f"the readings of l{j + 1} spread {spread[j] * 1e3:.4g} mm around their median{widest}, the nominal robot's "
        f"TCP at the same joints {reference * 1e3:.4g} mm (ratio {ratio:.3g}): {hint}",
        path=data.source, column=f"l{j + 1}",
    )


def check_solvable(data: TracerData) -> None:
    """Raise :class:`DataError` when the lengths cannot determine points, stations and dead paths.

    Counts only measured lengths: every station needs :data:`MIN_POSES_PER_STATION` poses, and the
    ``n`` poses seen by at least three stations need ``K >= 3n + 4m - 6 + 1`` lengths among them.
    """
    seen = data.seen
    _, m = seen.shape
    per_station = seen.sum(0)
    for j in range(m):
        if int(per_station[j]) < MIN_POSES_PER_STATION:
            raise DataError(
                f"station {j + 1} saw only {int(per_station[j])} pose(s); a station needs at least "
                f"{MIN_POSES_PER_STATION} (position and dead path are 4 unknowns, plus one to check them)",
                path=data.source, column=f"l{j + 1}",
            )
    located = seen.sum(1) >= MIN_STATIONS_PER_POSE
    n_loc = int(located.sum())
    k = int(seen[located].sum())
    need = 3 * n_loc + 4 * m - 6 + 1
    if k < need:
        poses = max(0, math.ceil((4 * m - 5 - (k - 3 * n_loc)) / max(m - 3, 1)))
        raise DataError(
            f"{k} lengths of {n_loc} pose(s) seen by at least {MIN_STATIONS_PER_POSE} of the {m} stations cannot "
            f"determine 3 coordinates per pose + 4 per station - 6 for the frame ({need - 1} unknowns) with one "
            f"to spare: measure about {poses} more pose(s) seen by every station (a pose seen by only 3 stations "
            "adds no redundancy)",
            path=data.source,
        )


def check_triangle_inequality(data: TracerData, robot: RobotModel, tolerance_m: float = 0.02) -> None:
    """Reject readings that change between two poses by more than the reflector can have moved.

    ``|l_ij - l_kj| <= |P_i - P_k|`` for any station ``j`` whatever its position and dead path;
    ``P`` is the nominal TCP, good to a few mm, hence the tolerance. The pose blamed is the one in
    most violating pairs of that station (a lost count or a wrong unit shows in many pairs).
    """
    p = robot.tcp_position(data.q)
    moved = torch.cdist(p, p)
    lengths = data.lengths
    for j in range(data.n_stations):
        col = lengths[:, j]
        seen = torch.isfinite(col)
        change = (col.unsqueeze(1) - col.unsqueeze(0)).abs()
        excess = torch.where(seen.unsqueeze(1) & seen.unsqueeze(0), change - moved, torch.zeros_like(change))
        bad = excess > tolerance_m
        if bool(bad.any()):
            counts = bad.sum(1)
            i = int(counts.argmax())
            k = int((excess[i]).argmax())
            raise DataError(
                f"station {j + 1}'s reading changes by {float(change[i, k]) * 1e3:.3f} mm between this pose and "
                f"row {data.line(k)}, but the nominal TCP moves only {float(moved[i, k]) * 1e3:.3f} mm "
                f"(triangle inequality, {int(counts[i])} pair(s) of this pose violate it): wrong length unit, "
                "swapped column, or a lost interferometer count",
                path=data.source, row=data.line(i), column=f"l{j + 1}",
            )
