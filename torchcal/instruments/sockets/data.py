"""Loading a socket file: ``placement, socket, q1..qN`` (joints in deg unless told otherwise).

One row per configuration of the robot with its ball in a socket. ``placement`` names where the
fixture stood (free text), ``socket`` which of its sockets (an integer, 0 and 1 for the usual
two-socket fixture). Each (placement, socket) pair is one *group*: one unknown ball-centre point.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchcal.core.errors import DataError
from torchcal.data.csv_table import check_units, joint_columns, read_csv_table
from torchcal.data.plausibility import check_joint_unit
from torchcal.kinematics.robot import RobotModel

REQUIRED = ("placement", "socket")


@dataclass(frozen=True)
class SocketData:
    """A validated socket file, SI units.

    Attributes:
        q: ``(n, N)`` joint angles, rad, in file order.
        placement: ``(n,)`` placement name of each row.
        socket: ``(n,)`` socket number of each row.
        group: ``(n,)`` long index into :attr:`groups` of each row.
        groups: ``(placement, socket)`` of every group, in order of first appearance.
        source / sha256: the file and its content hash.
        line_numbers: 1-based line of each row as a spreadsheet shows it.
    """

    q: torch.Tensor
    placement: tuple[str, ...]
    socket: tuple[int, ...]
    group: torch.Tensor
    groups: tuple[tuple[str, int], ...]
    source: str
    sha256: str
    line_numbers: tuple[int, ...]

    def __len__(self) -> int:
        return int(self.q.shape[0])

    @property
    def placements(self) -> tuple[str, ...]:
        """Placement names in order of first appearance."""
        return tuple(dict.fromkeys(self.placement))

    def pairs(self) -> list[tuple[str, int, int]]:
        """``(placement, group of the lower socket, group of the higher)`` for placements with >= 2 sockets.

        With more than two sockets only the two lowest-numbered are paired (the fixture's known distance).
        """
        out = []
        for name in self.placements:
            members = sorted((s, g) for g, (p, s) in enumerate(self.groups) if p == name)
            if len(members) >= 2:
                out.append((name, members[0][1], members[1][1]))
        return out

    def subset(self, rows: np.ndarray | torch.Tensor | list[int]) -> SocketData:
        """The rows ``rows`` (indices) as a new data set; groups renumbered by first appearance."""
        idx = [int(i) for i in (rows.tolist() if hasattr(rows, "tolist") else rows)]
        placement = tuple(self.placement[i] for i in idx)
        socket = tuple(self.socket[i] for i in idx)
        return _assemble(self.q[idx], placement, socket, self.source, self.sha256,
                         tuple(self.line_numbers[i] for i in idx))

    def select_placements(self, names: list[str] | tuple[str, ...]) -> SocketData:
        """Rows of the named placements only (an unknown name is an error naming the file)."""
        unknown = [n for n in names if n not in self.placements]
        if unknown:
            raise DataError(f"no placement {unknown[0]!r} in the file; it has {list(self.placements)}", path=self.source)
        return self.subset([i for i, p in enumerate(self.placement) if p in set(names)])


def _assemble(q, placement, socket, source, sha256, lines) -> SocketData:
    groups: dict[tuple[str, int], int] = {}
    index = [groups.setdefault((p, s), len(groups)) for p, s in zip(placement, socket)]
    return SocketData(q=q, placement=placement, socket=socket, group=torch.tensor(index, dtype=torch.long),
                      groups=tuple(groups), source=source, sha256=sha256, line_numbers=lines)


def load_socket_data(path: str | Path, robot: RobotModel, *, joint_unit: str = "deg",
                     min_rows_per_group: int = 2, check_limits: bool = True) -> SocketData:
    """Read and validate a socket file against ``robot`` (joint count, joint unit, limits, group sizes).

    Every problem is a :class:`DataError` naming the file, row and column. ``check_limits=False``
    accepts joints outside the robot file's limits (recorded joints were reached by the robot, so
    such a row says the file's limits are narrower than the robot's).
    """
    path = Path(path)
    check_units(joint_unit, "mm", path)
    table = read_csv_table(path)
    header = tuple(h.lower() for h in table.header)
    table = type(table)(path=table.path, header=header, rows=table.rows, line_numbers=table.line_numbers)
    for name in REQUIRED:
        if name not in header:
            raise DataError(f"missing column '{name}' (a socket file has placement, socket, q1..qN)", path=str(path), row=1)
    joints = joint_columns(header, path, robot.dof, robot.name)
    scale = math.pi / 180.0 if joint_unit == "deg" else 1.0
    q_file = np.stack([table.column(j) for j in joints], -1)
    # radians read as degrees stay inside every limit and fit to a meaningless robot
    check_joint_unit(q_file, joint_unit, robot.joint_limits.numpy(), path=str(path), lines=table.line_numbers)
    q = torch.tensor(q_file * scale, dtype=torch.float64)
    p_idx, s_idx = header.index("placement"), header.index("socket")
    placement, socket = [], []
    for row, line in zip(table.rows, table.line_numbers):
        name = row[p_idx].strip()
        if not name:
            raise DataError("empty placement name", path=str(path), row=line, column="placement")
        cell = row[s_idx].strip()
        try:
            number = int(cell)
        except ValueError:
            raise DataError(f"socket must be an integer, got '{cell}'", path=str(path), row=line, column="socket") from None
        placement.append(name)
        socket.append(number)
    lim = robot.joint_limits
    slack = 1e-6
    outside = (q < lim[:, 0] - slack) | (q > lim[:, 1] + slack)
    if check_limits and bool(outside.any()):
        i, j = (int(v) for v in outside.nonzero()[0])
        unit = "deg" if joint_unit == "deg" else "rad"
        raise DataError(f"{float(q[i, j]) / scale:.4g} {unit} is outside the joint limits "
                        f"[{float(lim[j, 0]) / scale:.4g}, {float(lim[j, 1]) / scale:.4g}] of {robot.name} "
                        "(check_limits=false accepts it)",
                        path=str(path), row=table.line_numbers[i], column=joints[j])
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    data = _assemble(q, tuple(placement), tuple(socket), str(path), digest, tuple(table.line_numbers))
    counts = torch.bincount(data.group, minlength=len(data.groups))
    for g, (p, s) in enumerate(data.groups):
        if int(counts[g]) < min_rows_per_group:
            first = data.line_numbers[int((data.group == g).nonzero()[0])]
            raise DataError(f"placement {p!r} socket {s} has {int(counts[g])} row(s); a socket needs at least "
                            f"{min_rows_per_group} configurations", path=str(path), row=first, column="socket")
    return data
