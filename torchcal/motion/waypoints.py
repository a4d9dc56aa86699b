"""A TCP path from a waypoint file: straight lines with slerped orientation, in the robot base frame.

File (CSV, header row, one waypoint per row): ``x, y, z`` (mm) and ``rx, ry, rz`` (deg, fixed-axis
XYZ: ``R = Rz(rz) Ry(ry) Rx(rx)``) of the TCP in the robot ``base`` frame. Consecutive waypoints
are joined by a straight line of the TCP position while the orientation turns at a constant rate
about one axis (slerp); the robot stops at every waypoint (the lines meet at corners, where a
continuous joint velocity needs zero TCP speed).

The path parameter ``s`` (m) runs from 0 to :attr:`WaypointPath.length`. Segment ``i`` covers
``ell_i = max(L_i, theta_i * speed / angular_speed)``: its line length, or, for a turn with little
or no travel, the length that keeps the orientation within the angular speed when ``ds/dt`` is
within the path speed. So ``ds/dt <= speed`` bounds both the TCP speed and its angular speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchcal.core.errors import DataError
from torchcal.data.csv_table import read_csv_table
from torchcal.kinematics import transforms as tf

COLUMNS = ("x", "y", "z", "rx", "ry", "rz")
_MAX_TURN_RAD = math.pi - 1e-3  # slerp between waypoints needs a unique shortest rotation
_MIN_MOVE_M = 1e-9


@dataclass(frozen=True)
class Waypoints:
    """Waypoint poses read from a file.

    Attributes:
        poses: ``(M, 4, 4)`` TCP poses ``T_base_tool``, m.
        lines: file line of each waypoint (header = line 1), for messages.
        path: the file.
    """

    poses: torch.Tensor
    lines: tuple[int, ...]
    path: Path


def load_waypoints(path: str | Path, device: str | torch.device = "cpu") -> Waypoints:
    """Read and check a waypoint file (module docstring); every problem names file, row and column.

    Raises:
        DataError: missing or unknown columns, a non-number, fewer than 2 waypoints, a waypoint
            equal to the one before it, or a turn of 180 deg or more between two waypoints.
    """
    table = read_csv_table(path)
    where = str(table.path)
    lower = {h.lower(): h for h in table.header}
    for name in COLUMNS:
        if name not in table.header:
            hint = f" (found '{lower[name]}': column names are lower case)" if name in lower else ""
            raise DataError(f"missing column '{name}'{hint}; a path file needs columns {', '.join(COLUMNS)}",
                            path=where, row=1)
    extra = [h for h in table.header if h not in COLUMNS]
    if extra:
        raise DataError(f"unknown column(s) {extra}; a path file has columns {', '.join(COLUMNS)}",
                        path=where, row=1, column=extra[0])
    values = torch.from_numpy(np.stack([table.column(name) for name in COLUMNS], 1))
    if values.shape[0] < 2:
        raise DataError("a path needs at least 2 waypoints", path=where, row=table.line_numbers[0])
    rotation = tf.euler_xyz_to_matrix(values[:, 3:] * (math.pi / 180.0))
    poses = tf.homogeneous(rotation, values[:, :3] * 1e-3)
    lines = tuple(table.line_numbers)
    for k in range(1, len(lines)):
        move = float((poses[k, :3, 3] - poses[k - 1, :3, 3]).norm())
        turn = float(tf.rotation_angle(poses[k, :3, :3] @ poses[k - 1, :3, :3].T))
        if move < _MIN_MOVE_M and turn < _MIN_MOVE_M:
            raise DataError(f"waypoint repeats the one on row {lines[k - 1]}", path=where, row=lines[k])
        if turn > _MAX_TURN_RAD:
            raise DataError(f"turns the tool by {math.degrees(turn):.2f} deg from row {lines[k - 1]}; slerp needs less "
                            "than 180 deg between waypoints (add one in between)", path=where, row=lines[k], column="rx")
    return Waypoints(poses=poses.to(device), lines=lines, path=table.path)


class WaypointPath:
    """The straight-line, slerp-orientation path through waypoint poses (module docstring).

    Args:
        poses: ``(M, 4, 4)`` waypoint poses, m.
        speed: path speed that ``ell_i`` is scaled for, m/s.
        angular_speed: largest tool angular speed, rad/s.
    """

    def __init__(self, poses: torch.Tensor, speed: float, angular_speed: float) -> None:
        self.poses = poses.to(torch.float64)
        p, r = self.poses[:, :3, 3], self.poses[:, :3, :3]
        self.delta = p[1:] - p[:-1]  # (M-1, 3)
        self.rotvec = tf.so3_log(r[1:] @ r[:-1].transpose(-1, -2))  # (M-1, 3), base frame
        lengths = self.delta.norm(dim=-1)
        angles = self.rotvec.norm(dim=-1)
        self.ell = torch.maximum(lengths, angles * (speed / angular_speed))
        self.knots = torch.cat([self.ell.new_zeros(1), torch.cumsum(self.ell, 0)])  # s of each waypoint

    @property
    def length(self) -> float:
        """Total path parameter, m."""
        return float(self.knots[-1])

    def segment(self, s: torch.Tensor) -> torch.Tensor:
        """Segment index ``(...)`` of path parameters ``s`` ``(...)`` (the last one owns its end)."""
        idx = torch.searchsorted(self.knots, s.contiguous(), right=True) - 1
        return idx.clamp(0, len(self.ell) - 1)

    def poses_at(self, s: torch.Tensor) -> torch.Tensor:
        """Desired TCP poses ``(..., 4, 4)`` at ``s`` ``(...)``."""
        s = s.to(self.poses)
        i = self.segment(s)
        lam = ((s - self.knots[i]) / self.ell[i]).clamp(0.0, 1.0)
        p = self.poses[i, :3, 3] + lam.unsqueeze(-1) * self.delta[i]
        r = tf.so3_exp(lam.unsqueeze(-1) * self.rotvec[i]) @ self.poses[i, :3, :3]
        return tf.homogeneous(r, p)

    def tangent(self, s: torch.Tensor) -> torch.Tensor:
        """``d(pose)/ds`` ``(..., 6)``: linear (m/m) and angular (rad/m) rates, base frame."""
        i = self.segment(s.to(self.poses))
        return torch.cat([self.delta[i], self.rotvec[i]], -1) / self.ell[i].unsqueeze(-1)


def waypoints_csv(poses: torch.Tensor) -> str:
    """The path file text of waypoint poses ``(M, 4, 4)`` (m): ``x, y, z`` mm, ``rx, ry, rz`` deg."""
    angles = tf.matrix_to_euler_xyz(poses[:, :3, :3].to(torch.float64)) * (180.0 / math.pi)
    rows = torch.cat([poses[:, :3, 3].to(torch.float64) * 1e3, angles], -1).tolist()
    return "\n".join([",".join(COLUMNS)] + [",".join(f"{v:.12g}" for v in row) for row in rows]) + "\n"
