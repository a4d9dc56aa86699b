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

A file in the wrong unit parses cleanly and fits (or scores) a meaningless stiffness, so the size
of the loads and deflections is compared with what an industrial arm on a loading rig can show
(:func:`check_plausible_units`): forces in kN, torques in N mm, deflections in m or um and
rotations in rad are refused with the likely unit.
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

# Plausible ranges on a loading rig for industrial arms (the file's largest value of each group,
# SI after the file's units are applied). Industrial arms are about 0.1-10 N/um stiff at the TCP
# and a tracker resolves about 10 um, so a useful test load is tens of N or more; the heaviest arms
# carry about 2.3 t (23 kN, about 11 kN m at a 0.5 m lever) and deflect a few mm under it.
#: Largest force below this (N): the forces look like kN (a real test load of up to 5 kN would read < 5).
MIN_FORCE_N = 5.0
#: Largest force above this (N): more than twice what the heaviest industrial arm carries.
MAX_FORCE_N = 50e3
#: Largest moment above this (N m): about twice the wrist moment of the heaviest arms; N mm likely.
MAX_TORQUE_NM = 20e3
#: Largest moment / largest force above this (m): no rig loads the TCP through a lever this long
#: (the reach of the largest arms is about 4 m), while a moment in N mm reads 1000 times its size.
MAX_TORQUE_LEVER_M = 5.0
#: Largest deflection below this (m, 5 um): under a tracker's resolution, nothing to fit; any
#: deflection below 5 mm written in m reads below it.
MIN_DEFLECTION_M = 5e-6
#: Largest deflection above this (m, 25 mm): far beyond the elastic deflection of an arm under its
#: rated load; any deflection above 25 um written in um reads above it.
MAX_DEFLECTION_M = 25e-3
#: Largest deflection / largest rotation above this (m): a rotation of the TCP moves it by at most
#: the distance from the yielding joint, i.e. the arm's reach (about 4 m for the largest arms), while
#: rotations in rad read as deg look 57 times too small (a twin rig shows 0.3-0.8 m).
MAX_DEFLECTION_LEVER_M = 5.0


def _group(header: tuple[str, ...], names: tuple[str, ...], path: str, what: str, required: bool) -> bool:
    present = [c for c in names if c in header]
    missing = [c for c in names if c not in header]
    if required and missing:
        raise DataError(f"missing column(s) {missing}; a stiffness file needs {what}", path=path, row=1, column=missing[0])
    if present and missing:
        raise DataError(f"{what} needs all of {list(names)}; found only {present}", path=path, row=1, column=missing[0])
    return not missing


def _largest(block: torch.Tensor, lines: list[int], names: tuple[str, ...]) -> tuple[float, int, str]:
    """Largest row norm of ``block`` ``(B, 3)``, its line and the column of that row's largest entry."""
    norms = block.norm(dim=-1)
    k = int(norms.argmax())
    return float(norms[k]), lines[k], names[int(block[k].abs().argmax())]


def check_plausible_units(data: StiffnessData, lines: list[int], length_unit: str = "mm") -> None:
    """Refuse a stiffness file whose loads or deflections are implausible for an industrial arm.

    Compares the file's largest force (N), moment (N m), deflection (m) and, when present, rotation
    (rad) with the ranges above, in that order (a ratio check needs its denominator in the right
    unit), and names the unit the values most likely are in.

    Args:
        data: the file as read, SI (``wrench`` N, N m; ``deflection`` m; ``rotation`` rad).
        lines: the file line of each row (the header is line 1).
        length_unit: the unit the ``d*`` columns were read in (``mm`` or ``m``), for the message.

    Raises:
        DataError: naming the file, the row and column of the largest value, the columns and the
            likely unit.
    """
    p = data.path
    force, line, col = _largest(data.wrench[:, :3], lines, WRENCH_COLUMNS[:3])
    torque, t_line, t_col = _largest(data.wrench[:, 3:], lines, WRENCH_COLUMNS[3:])
    if 0.0 < force < MIN_FORCE_N:
        # a moment column just as small says the whole wrench is in kN, kN m
        what = "the wrenches look like kN and kN m" if 0.0 < torque < MIN_FORCE_N * 0.1 else "the forces look like kN"
        raise DataError(
            f"the forces fx, fy, fz reach only {force:.4g} N (a rig load is at least {MIN_FORCE_N:g} N): {what}; "
            "a stiffness file gives N and N m", path=p, row=line, column=col)
    if force > MAX_FORCE_N:
        raise DataError(
            f"the forces fx, fy, fz reach {force:.4g} N, more than {MAX_FORCE_N:g} N (above any industrial arm's "
            "payload): check their unit; a stiffness file gives N", path=p, row=line, column=col)
    if torque > MAX_TORQUE_NM or (force > 0.0 and torque / force > MAX_TORQUE_LEVER_M):
        lever = f", {torque / force:.3g} m times the largest force" if force > 0.0 else ""
        raise DataError(
            f"the moments tx, ty, tz reach {torque:.4g} N m{lever} (plausible: up to {MAX_TORQUE_NM:g} N m and "
            f"{MAX_TORQUE_LEVER_M:g} m times the force): the moments look like N mm; a stiffness file gives N m",
            path=p, row=t_line, column=t_col)
    size, line, col = _largest(data.deflection, lines, DEFLECTION_COLUMNS)
    shown = f"{size * 1e3:.4g} mm" if length_unit == "mm" else f"{size:.4g} m ({size * 1e3:.4g} mm)"
    if size < MIN_DEFLECTION_M:
        hint = "the deflections look like m; a stiffness file gives mm (or set length_unit=m)" if length_unit == "mm" else "check their unit"
        raise DataError(
            f"the deflections dx, dy, dz reach only {shown}, below the {MIN_DEFLECTION_M * 1e3:g} mm a tracker "
            f"resolves: {hint}", path=p, row=line, column=col)
    if size > MAX_DEFLECTION_M:
        hint = "the deflections look like um; a stiffness file gives mm" if length_unit == "mm" else (
            "the deflections look like mm; set length_unit=mm")
        raise DataError(
            f"the deflections dx, dy, dz reach {shown}, more than the {MAX_DEFLECTION_M * 1e3:g} mm an arm "
            f"deflects elastically: {hint}", path=p, row=line, column=col)
    if data.rotation is not None:
        angle, line, col = _largest(data.rotation, lines, ROTATION_COLUMNS)
        if angle > 0.0 and size / angle > MAX_DEFLECTION_LEVER_M:
            raise DataError(
                f"the rotations drx, dry, drz reach only {math.degrees(angle):.4g} deg while the deflections reach "
                f"{size * 1e3:.4g} mm: a lever of {size / angle:.3g} m, beyond any arm's reach "
                f"({MAX_DEFLECTION_LEVER_M:g} m): the rotations look like rad; a stiffness file gives deg",
                path=p, row=line, column=col)


def load_stiffness(
    path: str | Path,
    *,
    n_joints: int | None = None,
    joint_unit: str = "deg",
    length_unit: str = "mm",
    device: str | torch.device = "cpu",
    check_plausible: bool = True,
) -> StiffnessData:
    """Read and validate a stiffness file of the data contract.

    Args:
        path: CSV file.
        n_joints: expected number of joints (the robot's); ``None`` accepts any.
        joint_unit: ``"deg"`` (contract default) or ``"rad"`` for ``q*``.
        length_unit: ``"mm"`` (contract default) or ``"m"`` for ``d*`` and ``x, y, z``.
        device: where the tensors are created.
        check_plausible: refuse loads and deflections outside what an industrial arm shows
            (:func:`check_plausible_units`: a unit mistake).

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
    data = StiffnessData(
        q=block(joints) * angle,
        wrench=wrench,
        deflection=block(DEFLECTION_COLUMNS) * length,
        rotation=block(ROTATION_COLUMNS) * (math.pi / 180.0) if has_rot else None,
        unloaded=block(POSITION_COLUMNS) * length if has_pos else None,
        path=p,
    )
    if check_plausible:
        check_plausible_units(data, lines, length_unit)
    return data
