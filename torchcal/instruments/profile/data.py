"""Loader of the profile-scan file (data contract) -> validated SI tensors, one record per scan.

Columns (header row, one profile point per row):

==============  ==============================================================  =========
``scan``        scan label; every row of a scan shares the robot pose             integer
``q1..qN``      commanded joints of the scan                                      deg (rad)
``u``           point along the laser line, ``sensor`` frame x                    mm (m)
``w``           depth of the point, ``sensor`` frame z                            mm (m)
``plane``       optional: placement of the plane target the scan saw             integer
==============  ==============================================================  =========

A scan is identified by its ``(plane, scan)`` pair, so scan labels may restart for each
placement. Every problem raises a :class:`~torchcal.core.errors.DataError` naming the file, the line
(the header is line 1) and the column.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchcal.core.errors import DataError
from torchcal.core.hashing import sha256_file
from torchcal.core.io import atomic_write_text
from torchcal.data.csv_table import (
    CsvTable,
    check_joint_limits,
    check_units,
    joint_columns,
    read_csv_table,
)

REQUIRED = ("scan", "u", "w")
OPTIONAL = ("plane",)
#: A profile sensor's line covers tens to hundreds of mm: when no scan of a file spans this much
#: (m), its ``u, w`` were written in metres and read as mm.
MIN_WIDEST_SCAN_M = 1e-3


@dataclass(frozen=True)
class ProfileData:
    """Profile scans in SI units, float64.

    Attributes:
        q: ``(S, N)`` joints of each scan, rad.
        plane: ``(S,)`` long, 0-based placement index of each scan (into ``plane_labels``).
        point_scan: ``(K,)`` long, scan index of each point.
        uw: ``(K, 2)`` points ``(u, w)`` in the ``sensor`` frame's x-z plane, m.
        scan_labels: file label of each scan.
        plane_labels: file label of each placement (``0`` when the file has no ``plane`` column).
        scan_lines: first file line of each scan (for messages).
        point_lines: file line of each point.
        path: source file, if any.
        sha256: hash of the file's bytes, if read from one.
    """

    q: torch.Tensor
    plane: torch.Tensor
    point_scan: torch.Tensor
    uw: torch.Tensor
    scan_labels: tuple[str, ...]
    plane_labels: tuple[str, ...]
    scan_lines: tuple[int, ...] = ()
    point_lines: tuple[int, ...] = ()
    path: str | None = None
    sha256: str | None = None

    def __len__(self) -> int:
        """Rows of the file: one per measured point."""
        return self.n_points

    @property
    def n_scans(self) -> int:
        return int(self.q.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.uw.shape[0])

    @property
    def n_planes(self) -> int:
        return len(self.plane_labels)

    @property
    def n_joints(self) -> int:
        return int(self.q.shape[1])

    def point_plane(self) -> torch.Tensor:
        """``(K,)`` placement index of each point."""
        return self.plane[self.point_scan]

    def select_scans(self, keep: torch.Tensor) -> ProfileData:
        """The scans where ``keep`` ``(S,)`` is true, with their points (placements kept as they are)."""
        keep = keep.to(torch.bool).cpu()
        index = keep.nonzero().squeeze(-1)
        remap = torch.full((self.n_scans,), -1, dtype=torch.long)
        remap[index] = torch.arange(index.numel())
        points = keep[self.point_scan.cpu()]
        lines = [ln for ln, k in zip(self.point_lines, points.tolist()) if k] if self.point_lines else []
        return ProfileData(
            q=self.q[index.to(self.q.device)],
            plane=self.plane[index.to(self.plane.device)],
            point_scan=remap[self.point_scan.cpu()[points]].to(self.point_scan.device),
            uw=self.uw[points.to(self.uw.device)],
            scan_labels=tuple(self.scan_labels[i] for i in index.tolist()),
            plane_labels=self.plane_labels,
            scan_lines=tuple(self.scan_lines[i] for i in index.tolist()) if self.scan_lines else (),
            point_lines=tuple(lines),
            path=self.path,
            sha256=self.sha256,
        )

    def describe_scan(self, j: int) -> str:
        """``scan '<label>' (plane <label>, line <n>)`` for messages."""
        where = f", line {self.scan_lines[j]}" if self.scan_lines else ""
        return f"scan '{self.scan_labels[j]}' (plane {self.plane_labels[int(self.plane[j])]}{where})"


def _label(cell: str, table: CsvTable, line: int, column: str) -> str:
    """An integer label, normalized (``'3.0'`` and ``'3'`` are the same scan)."""
    text = cell.strip()
    if text == "":
        raise DataError("empty cell", path=str(table.path), row=line, column=column)
    try:
        value = float(text)
    except ValueError:
        raise DataError(f"'{text}' is not an integer label", path=str(table.path), row=line, column=column) from None
    if not math.isfinite(value) or value != int(value):
        raise DataError(f"'{text}' is not an integer label", path=str(table.path), row=line, column=column)
    return str(int(value))


def _check_scan_size(uw: np.ndarray, point_scan: np.ndarray, n_scans: int, length_unit: str, *, path: str,
                     line: list[int], label: list[str]) -> None:
    """Refuse ``u, w`` read as mm whose widest scan spans under :data:`MIN_WIDEST_SCAN_M`.

    Args:
        uw: ``(K, 2)`` points as read, m; ``point_scan`` ``(K,)`` their scan index.
        line / label: first file line and label of each scan (for the message).
    """
    if length_unit != "mm":
        return
    low = np.full((n_scans, 2), np.inf)
    high = np.full((n_scans, 2), -np.inf)
    np.minimum.at(low, point_scan, uw)
    np.maximum.at(high, point_scan, uw)
    extent = np.linalg.norm(high - low, axis=1)  # bounding-box diagonal of each scan, m
    s = int(extent.argmax())
    if float(extent[s]) >= MIN_WIDEST_SCAN_M:
        return
    raise DataError(
        f"the widest scan ('{label[s]}') spans only {extent[s] * 1e3:.3g} mm in (u, w), while a profile sensor "
        "measures over tens to hundreds of mm: u, w look like metres; set length_unit=m",
        path=path, row=line[s], column="u",
    )


def load_profile(
    path: str | Path,
    *,
    n_joints: int | None = None,
    joint_limits_rad: torch.Tensor | None = None,
    joint_unit: str = "deg",
    length_unit: str = "mm",
    limit_tolerance_deg: float = 0.01,
    device: str | torch.device = "cpu",
) -> ProfileData:
    """Read and validate a profile-scan file of the data contract.

    Args:
        path: CSV file.
        n_joints: expected number of joints (the robot's); ``None`` accepts any.
        joint_limits_rad: ``(N, 2)`` limits to check the joints against; ``None`` skips it.
        joint_unit: ``"deg"`` (contract default) or ``"rad"`` for ``q*``.
        length_unit: ``"mm"`` (contract default) or ``"m"`` for ``u, w``.
        limit_tolerance_deg: how far outside a limit a joint may be (rounding in files).
        device: where the tensors are created.

    Raises:
        DataError: file, line and column of the first problem found: missing or unknown
            columns, empty / non-numeric / non-finite cells, non-integer labels, a joint count
            that does not match the robot, joints outside the limits, rows of one scan with
            different joints, a scan with fewer than two distinct points, or ``u, w`` in mm
            whose widest scan spans less than 1 mm (metres read as mm).
    """
    check_units(joint_unit, length_unit, path)
    table = read_csv_table(path)
    p = str(table.path)
    header = table.header
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        lowered = {h.lower(): h for h in header}
        hint = f" (found '{lowered[missing[0]]}'; names are case-sensitive)" if missing[0] in lowered else ""
        raise DataError(f"missing column '{missing[0]}'{hint}; a profile file needs scan, q1..qN, u, w", path=p, row=1, column=missing[0])
    joints = joint_columns(header, p, n_joints)
    extra = [h for h in header if h not in set(REQUIRED) | set(OPTIONAL) | set(joints)]
    if extra:
        raise DataError(f"unknown column '{extra[0]}'; allowed: scan, q1..q{len(joints)}, u, w, plane", path=p, row=1, column=extra[0])

    lines = table.line_numbers
    q_file = np.stack([table.column(c) for c in joints], 1)
    length = 1e-3 if length_unit == "mm" else 1.0
    uw = np.stack([table.column("u"), table.column("w")], 1) * length
    scan_idx = header.index("scan")
    plane_idx = header.index("plane") if "plane" in header else None
    scan_of_row = [_label(row[scan_idx], table, line, "scan") for row, line in zip(table.rows, lines)]
    plane_of_row = (
        [_label(row[plane_idx], table, line, "plane") for row, line in zip(table.rows, lines)]
        if plane_idx is not None
        else ["0"] * len(lines)
    )

    # Scans keyed by (plane, scan) in order of first appearance; placements sorted numerically.
    plane_labels = tuple(sorted(set(plane_of_row), key=int))
    plane_index = {label: i for i, label in enumerate(plane_labels)}
    keys: dict[tuple[str, str], int] = {}
    point_scan = np.empty(len(lines), dtype=np.int64)
    first_row: list[int] = []
    for k, key in enumerate(zip(plane_of_row, scan_of_row)):
        if key not in keys:
            keys[key] = len(keys)
            first_row.append(k)
        point_scan[k] = keys[key]
    first = np.asarray(first_row)
    q_scan = q_file[first]
    deviation = np.abs(q_file - q_scan[point_scan])
    bad = deviation > 1e-9 * np.maximum(1.0, np.abs(q_scan[point_scan]))
    if bad.any():
        k, j = map(int, np.argwhere(bad)[0])
        s = int(point_scan[k])
        raise DataError(
            f"scan '{scan_of_row[k]}' was started at line {lines[first[s]]} with {joints[j]} = {q_file[first[s], j]:g}, "
            f"this row has {q_file[k, j]:g}: every row of a scan must share its robot pose",
            path=p, row=lines[k], column=joints[j],
        )

    angle = math.pi / 180.0 if joint_unit == "deg" else 1.0
    q = q_scan * angle
    if joint_limits_rad is not None:
        lim = joint_limits_rad.detach().cpu().numpy()
        if lim.shape[0] != q.shape[1]:
            raise DataError(f"has {q.shape[1]} joint columns but the robot has {lim.shape[0]} joints", path=p, row=1)
        check_joint_limits(q_scan, joint_unit, lim, path=p, lines=[lines[i] for i in first], columns=list(joints),
                           tolerance_deg=limit_tolerance_deg)

    # A scan needs two distinct points to give a line; one repeated point carries no direction.
    n_scans = len(keys)
    spread = np.zeros(n_scans)
    np.maximum.at(spread, point_scan, np.abs(uw - uw[first][point_scan]).max(1))
    scale = max(float(np.abs(uw).max()), 1e-3 * length)
    flat = np.nonzero(spread <= 1e-9 * scale)[0]
    if flat.size:
        s = int(flat[0])
        count = int((point_scan == s).sum())
        label = scan_of_row[first[s]]
        what = "one point" if count == 1 else f"{count} rows but a single distinct point"
        raise DataError(f"scan '{label}' has {what}; a scan needs at least two distinct (u, w) points", path=p, row=lines[first[s]], column="u")
    _check_scan_size(uw, point_scan, n_scans, length_unit, path=p, line=[lines[k] for k in first_row],
                     label=[scan_of_row[k] for k in first_row])

    plane = np.array([plane_index[plane_of_row[k]] for k in first_row], dtype=np.int64)
    return ProfileData(
        q=torch.from_numpy(q).to(device),
        plane=torch.from_numpy(plane).to(device),
        point_scan=torch.from_numpy(point_scan).to(device),
        uw=torch.from_numpy(uw).to(device),
        scan_labels=tuple(scan_of_row[k] for k in first_row),
        plane_labels=plane_labels,
        scan_lines=tuple(lines[k] for k in first_row),
        point_lines=tuple(lines),
        path=p,
        sha256=sha256_file(p),
    )


def profile_csv_text(data: ProfileData, *, with_plane: bool = True) -> str:
    """The contract CSV of ``data``: ``scan, q1..qN, u, w[, plane]`` in deg and mm."""
    n = data.n_joints
    header = ["scan"] + [f"q{i}" for i in range(1, n + 1)] + ["u", "w"] + (["plane"] if with_plane else [])
    q_deg = (data.q * (180.0 / math.pi)).cpu().tolist()
    uw_mm = (data.uw * 1e3).cpu().tolist()
    scans = data.point_scan.cpu().tolist()
    planes = data.plane.cpu().tolist()
    out = [",".join(header)]
    for k, s in enumerate(scans):
        cells = [data.scan_labels[s]] + [f"{v:.15g}" for v in q_deg[s]] + [f"{uw_mm[k][0]:.9f}", f"{uw_mm[k][1]:.9f}"]
        if with_plane:
            cells.append(data.plane_labels[planes[s]])
        out.append(",".join(cells))
    return "\n".join(out) + "\n"


def write_profile_csv(path: str | Path, data: ProfileData, *, with_plane: bool = True) -> Path:
    """Write ``data`` as a contract profile CSV, atomically."""
    path = Path(path)
    atomic_write_text(path, profile_csv_text(data, with_plane=with_plane))
    return path
