"""Which measurement kind a CSV holds, read from its header (see the data contract).

``tracker`` (``x,y,z``), ``tracer`` (``l1..lM``, M >= 2), ``length_station`` (``l1`` alone: one
draw-wire), ``stiffness`` (``fx..tz`` and ``dx,dy,dz``), ``profile`` (``scan``, ``u``, ``w``) and
``sockets`` (``placement``, ``socket``: joints only). ``torchcal fit`` and ``evaluate`` dispatch on
it, so a user never names the instrument: the columns tell.
"""

from __future__ import annotations

import csv
from pathlib import Path

from torchcal.errors import DataError

KINDS = ("tracker", "tracer", "stiffness", "profile", "sockets", "length_station")


def _header(path: Path) -> list[str]:
    if not path.is_file():
        raise DataError("file not found", path=str(path))
    with path.open(encoding="utf-8-sig", newline="") as handle:
        for row in csv.reader(handle):
            if any(cell.strip() for cell in row):
                return [cell.strip().lower() for cell in row]
    raise DataError("the file is empty (no header row)", path=str(path))


def measurement_kind(path: str | Path) -> str:
    """The measurement kind of the CSV at ``path``, from its column names."""
    path = Path(path)
    names = set(_header(path))
    if {"placement", "socket"} <= names:
        return "sockets"
    if {"scan", "u", "w"} <= names:
        return "profile"
    if {"fx", "fy", "fz", "tx", "ty", "tz", "dx", "dy", "dz"} <= names:
        return "stiffness"
    if "l1" in names:
        return "length_station" if "l2" not in names else "tracer"
    if {"x", "y", "z"} <= names:
        return "tracker"
    raise DataError(
        "cannot tell the measurement kind from the header: expected x,y,z (tracker), l1..lM (tracer), "
        "fx..tz with dx,dy,dz (stiffness), scan,u,w (profile) or placement,socket (sockets)",
        path=str(path),
        row=1,
    )
