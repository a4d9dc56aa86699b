"""Kinematic parameters re-derived from measured (or parsed) joint axes: the axis method.

Given each joint axis as a line in one common frame (``base``) with the robot at its zero
configuration, build Craig frames on the axes (common normals) and read the MDH parameters off
consecutive frames. Where two consecutive axes are within ``parallel_threshold_rad`` of parallel
the common normal is ill-defined; there the Hayati rule applies: frame ``i`` keeps the origin
where the perpendicular from the previous origin meets axis ``i``, and the tilt between the two
axes goes into ``beta`` instead of an enormous ``d``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcal.kinematics import transforms as tf
from torchcal.kinematics.mdh import decompose_link

DEFAULT_PARALLEL_THRESHOLD_RAD = 1e-3
"""Axes closer than this to parallel (about 0.057 deg) are treated with Hayati's beta."""


@dataclass(frozen=True)
class AxisFrames:
    """Result of the axis method.

    Attributes:
        table: ``(N, 5)`` rows ``[alpha, a, beta, theta_offset, d]`` (rad, m).
        T_base_0: ``(4, 4)`` fixed transform from ``base`` to MDH frame 0.
        T_n_flange: ``(4, 4)`` fixed transform from MDH frame N to ``flange``.
        frames: ``(N, 4, 4)`` the constructed joint frames in ``base`` (zero configuration).
    """

    table: torch.Tensor
    T_base_0: torch.Tensor
    T_n_flange: torch.Tensor
    frames: torch.Tensor


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm()


def _closest_points(p1, z1, p2, z2):
    """Closest points of two non-parallel lines ``p + t z`` (unit z)."""
    w = p1 - p2
    b = z1 @ z2
    d, e = z1 @ w, z2 @ w
    denom = 1.0 - b * b
    t1 = (b * e - d) / denom
    t2 = (e - b * d) / denom
    return p1 + t1 * z1, p2 + t2 * z2


def _project_on_line(point, origin, direction):
    return origin + ((point - origin) @ direction) * direction


def _frame(origin, x_axis, z_axis) -> torch.Tensor:
    y_axis = torch.linalg.cross(z_axis, x_axis)
    rotation = torch.stack([x_axis, y_axis, z_axis], -1)
    return tf.homogeneous(rotation, origin)


def _perpendicular(v: torch.Tensor, z: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    """Component of ``v`` orthogonal to ``z``, normalized; ``fallback`` when it vanishes."""
    w = v - (v @ z) * z
    if w.norm() < 1e-9:
        w = fallback - (fallback @ z) * z
    return _unit(w)


def mdh_from_axes(
    points: torch.Tensor,
    directions: torch.Tensor,
    T_base_flange: torch.Tensor,
    *,
    parallel_threshold_rad: float = DEFAULT_PARALLEL_THRESHOLD_RAD,
) -> AxisFrames:
    """Derive an MDH(+beta) table from joint axes given in the ``base`` frame at zero configuration.

    Args:
        points: ``(N, 3)`` a point on each joint axis, m, ``base`` frame.
        directions: ``(N, 3)`` each axis direction (positive joint rotation, right hand).
        T_base_flange: ``(4, 4)`` flange pose at the zero configuration.
        parallel_threshold_rad: below this angle between consecutive axes, use Hayati's beta.

    Returns:
        :class:`AxisFrames`. Chaining ``T_base_0``, the table at ``q = 0`` and ``T_n_flange``
        reproduces ``T_base_flange`` exactly, and every axis is the given line.
    """
    points = points.to(torch.float64)
    directions = torch.stack([_unit(d) for d in directions.to(torch.float64)])
    T_base_flange = T_base_flange.to(torch.float64)
    n = points.shape[0]
    base_x = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    base_y = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)

    origins: list[torch.Tensor] = []
    x_axes: list[torch.Tensor] = []
    # Where the previous frame's x axis meets axis i; frame 0 sits where the base origin
    # projects onto axis 1.
    entry = _project_on_line(torch.zeros(3, dtype=torch.float64), points[0], directions[0])
    prev_x = _perpendicular(base_x, directions[0], base_y)
    for i in range(n):
        z_i = directions[i]
        if i == n - 1:
            origin = _project_on_line(T_base_flange[:3, 3], points[i], z_i)
            x_i = _perpendicular(prev_x, z_i, T_base_flange[:3, 0])
            next_entry = origin
        else:
            z_next = directions[i + 1]
            sin_angle = torch.linalg.cross(z_i, z_next).norm()
            if sin_angle < parallel_threshold_rad:
                # Hayati: keep the origin where the previous normal arrived and go
                # perpendicular to z_i until axis i+1 is hit.
                origin = entry
                t = ((origin - points[i + 1]) @ z_i) / (z_next @ z_i)
                next_entry = points[i + 1] + t * z_next
                x_i = _perpendicular(next_entry - origin, z_i, prev_x)
            else:
                origin, next_entry = _closest_points(points[i], z_i, points[i + 1], z_next)
                offset = next_entry - origin
                if offset.norm() > 1e-9:
                    x_i = _unit(offset - (offset @ z_i) * z_i)
                else:
                    x_i = _unit(torch.linalg.cross(z_i, z_next))
                    if x_i @ prev_x < 0:  # keep the sign that needs the smaller theta offset
                        x_i = -x_i
        origins.append(origin)
        x_axes.append(x_i)
        entry, prev_x = next_entry, x_i

    frames = torch.stack([_frame(o, x, z) for o, x, z in zip(origins, x_axes, directions)])
    # Frame 0 shares axis 1 (Craig's choice), so row 1 carries only theta_1 and d_1.
    x0 = _perpendicular(base_x, directions[0], base_y)
    origin0 = _project_on_line(torch.zeros(3, dtype=torch.float64), points[0], directions[0])
    T_base_0 = _frame(origin0, x0, directions[0])
    previous = torch.cat([T_base_0.unsqueeze(0), frames[:-1]])
    relative = tf.invert(previous) @ frames
    table = decompose_link(relative)
    T_n_flange = tf.invert(frames[-1]) @ T_base_flange
    return AxisFrames(table=table, T_base_0=T_base_0, T_n_flange=T_n_flange, frames=frames)
