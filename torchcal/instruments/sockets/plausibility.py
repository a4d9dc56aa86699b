"""Plausibility of socket data against the nominal robot, and of a fit against its data.

A socket file has no measured coordinates, so a file in the wrong unit, with two placements
under one name or recorded on another robot parses cleanly and fits to a meaningless robot. What
the nominal robot does at the file's joints says whether the file can describe this robot:

* **consistency**: every configuration of one (placement, socket) put the ball at one point, so
  the nominal ball centres of a group lie within what an uncalibrated arm misses by (a few mm;
  tens of mm with an unmodelled tool). Far beyond that: wrong robot, wrong joint unit or order,
  or two placements merged under one name;
* **distortion**: the nominal robot measures the fixture's short socket distance to a few mm; a
  distance far from ``distance_mm`` is a wrong ``distance_mm`` (metres given as mm) or wrong
  socket numbers;
* **equations**: ``3`` per configuration plus ``1`` per two-socket placement against the unknowns
  (``3`` per point, the robot parameters, joint-space terms);
* **the fit itself**: a calibrated robot that misses its own configurations by more than the
  nominal robot describes nothing.

Every finding is a :class:`~torchcal.core.errors.DataError` naming the file (and row) and the
likely cause; too few equations per unknown only warns (as a tracker fit does).
"""

from __future__ import annotations

import math

import torch

from torchcal.core.errors import DataError
from torchcal.instruments.sockets.data import SocketData
from torchcal.instruments.sockets.model import group_means

#: Mean distance (mm) of a group's nominal ball centres (ball offset fitted) from their mean beyond which the
#: file is refused. Measured on the MUKCa recordings (nominal URDF to ball_link, per-group mean): kuka_14 <= 0.96,
#: dinova_1/2 <= 11.2, panda_* <= 11.7, panda_1_with_sensor 24.3 (a sensor on the flange the URDF does
#: not model): 50 mm keeps a factor 2 above the worst real file, while a wrong robot (387 mm on the
#: twin robot with a Kinova file) or two fixtures under one name (about 100 mm on the twin) lie far beyond.
CONSISTENCY_LIMIT_MM = 50.0
#: A nominal socket distance off ``distance_mm`` by more than min(this, fraction x distance) is refused.
#: The real recordings' nominal distortion is at most 8.2 mm (panda_6; kuka_14 0.18) at 50 mm: an
#: uncalibrated arm measures a short distance to a few mm (its local scale and the ball offset).
DISTORTION_LIMIT_MM = 20.0
DISTORTION_LIMIT_FRACTION = 0.5
#: Fewer equations per unknown than this warns (as :data:`torchcal.stages.geometry.MIN_EQUATIONS_PER_PARAMETER`).
MIN_EQUATIONS_PER_UNKNOWN = 3.0
#: A fit whose consistency RMS exceeds the nominal's by more than this factor (+ 1 um round-off) is refused.
WORSE_FACTOR = 1.01

CAUSES = ("the wrong robot file (or end link / ball offset), joints in radians read as degrees (joint_unit) or in "
          "another order, or two placements under one name")


def equations(data: SocketData) -> int:
    """Scalar equations of the data: 3 per configuration + 1 per two-socket placement (the distance)."""
    return 3 * len(data) + len(data.pairs())


def configurations_needed(data: SocketData, n_unknowns: int) -> int:
    """Configurations that give :data:`MIN_EQUATIONS_PER_UNKNOWN` equations per unknown: each new
    configuration of an existing socket adds 3 equations and no unknown."""
    return math.ceil((MIN_EQUATIONS_PER_UNKNOWN * n_unknowns - len(data.pairs())) / 3)


def refuse_too_few(data: SocketData, n_points: int, n_robot: int, n_terms: int = 0) -> None:
    """Refuse data with no more equations than unknowns (nothing left to check the fit, no covariance).

    Args:
        n_points / n_robot / n_terms: point coordinates, candidate robot parameters and joint-space
            terms of the problem (before the identifiability analysis: an upper bound it only lowers).
    """
    e, m = equations(data), n_points + n_robot + n_terms
    if e > m:
        return
    terms = f" + {n_terms} joint-space terms" if n_terms else ""
    need = configurations_needed(data, m)
    raise DataError(f"{len(data)} configurations give {e} equations (3 per configuration + 1 per two-socket placement) "
                    f"for {m} unknowns ({n_points} point coordinates + {n_robot} robot parameters{terms}): too few to "
                    f"fit them; record at least {need} configurations", path=data.source)


def few_equations_warning(data: SocketData, n_unknowns: int) -> str | None:
    """A warning when the data give fewer than :data:`MIN_EQUATIONS_PER_UNKNOWN` equations per fitted unknown."""
    e = equations(data)
    ratio = e / max(n_unknowns, 1)
    if ratio >= MIN_EQUATIONS_PER_UNKNOWN:
        return None
    need = configurations_needed(data, n_unknowns)
    return (f"{len(data)} configurations give {e} equations for {n_unknowns} unknowns ({ratio:.2f} per unknown): "
            f"the fit follows the noise; record at least {need} configurations")


def _two_blocks(centres: torch.Tensor) -> tuple[int, float, float] | None:
    """Best split of a group's rows (file order) into two runs: ``(first row of run 2, its spread, distance)``.

    ``centres``: ``(n, 3)`` nominal ball centres of one group, m. Returns the split (distances in mm)
    whose two runs stay within :data:`CONSISTENCY_LIMIT_MM` of their own means, or ``None``: two
    placements merged under one name look like that.
    """
    n = centres.shape[0]
    best = None
    for k in range(2, n - 1):  # each run keeps >= 2 rows
        a, b = centres[:k], centres[k:]
        ma, mb = a.mean(0), b.mean(0)
        spread = float(torch.cat([(a - ma).norm(dim=-1), (b - mb).norm(dim=-1)]).mean()) * 1e3
        if best is None or spread < best[1]:
            best = (k, spread, float((ma - mb).norm()) * 1e3)
    if best is None or best[1] > CONSISTENCY_LIMIT_MM:
        return None
    return best


def ball_centres(end_poses: torch.Tensor, group: torch.Tensor, n_groups: int) -> torch.Tensor:
    """``(n, 3)`` ball centres ``p + R t`` of the nominal chain's end poses ``(n, 4, 4)`` (m), with the
    ball offset ``t`` (end frame) and the group points fitted by linear least squares: the fit
    identifies the ball offset itself, so a robot file that ends at the flange is judged by what
    no offset explains (a ball 180 mm out would otherwise spread the centres by ~120 mm)."""
    rotation, position = end_poses[:, :3, :3], end_poses[:, :3, 3]
    n = position.shape[0]
    a = torch.zeros(n, 3, 3 + 3 * n_groups, dtype=torch.float64)
    a[:, :, :3] = rotation
    for k in range(3):
        a[torch.arange(n), k, 3 + 3 * group + k] = -1.0
    solution = torch.linalg.lstsq(a.reshape(3 * n, -1), -position.reshape(3 * n, 1)).solution
    return position + rotation @ solution[:3, 0]


def check_nominal(end_poses: torch.Tensor, data: SocketData, distance_mm: float, robot_name: str) -> None:
    """Refuse socket data the nominal robot cannot have recorded (see the module docstring).

    Args:
        end_poses: ``(n, 4, 4)`` poses of the nominal chain's end (its tool frame) at the data's joints, m;
            the ball offset from it is fitted (:func:`ball_centres`).
        distance_mm: the fixture's socket distance, mm.
    """
    group = data.group.cpu()
    centres = ball_centres(end_poses.detach().to(torch.float64).cpu(), group, len(data.groups))
    means = group_means(centres, group, len(data.groups))
    dist = (centres - means[group]).norm(dim=-1) * 1e3
    for g, (p, s) in enumerate(data.groups):
        rows = (group == g).nonzero().flatten()
        spread = float(dist[rows].mean())
        if spread <= CONSISTENCY_LIMIT_MM:
            continue
        lines = [data.line_numbers[int(i)] for i in rows]
        split = _two_blocks(centres[rows])
        if split is not None:
            k, _, apart = split
            raise DataError(f"placement {p!r} socket {s}: the nominal {robot_name} puts rows {lines[0]}-{lines[k - 1]} "
                            f"and {lines[k]}-{lines[-1]} at two points {apart:.0f} mm apart: likely two placements under "
                            "one name (give each its own placement name)",
                            path=data.source, row=lines[k], column="placement")
        raise DataError(f"placement {p!r} socket {s}: the nominal {robot_name} puts the ball centres of these "
                        f"{len(lines)} configurations {spread:.1f} mm (mean) from their common point, where an "
                        f"uncalibrated arm misses by at most tens of mm ({CONSISTENCY_LIMIT_MM:g}); likely {CAUSES}",
                        path=data.source, row=lines[0])
    limit = min(DISTORTION_LIMIT_MM, DISTORTION_LIMIT_FRACTION * distance_mm)
    for name, a, b in data.pairs():
        apart = float((means[a] - means[b]).norm()) * 1e3
        if abs(apart - distance_mm) <= limit:
            continue
        ratio = apart / distance_mm
        if 300 < ratio < 3000:
            hint = f"distance_mm looks like metres (distance_mm={distance_mm * 1e3:g}?)"
        else:
            hint = ("check distance_mm (the fixture's socket-to-socket distance, mm), the socket numbers, the joint unit "
                    "(radians read as degrees shrink every motion) and the robot file")
        first = data.line_numbers[int((data.group == b).nonzero()[0])]
        raise DataError(f"placement {name!r}: the nominal {robot_name} puts sockets {data.groups[a][1]} and "
                        f"{data.groups[b][1]} {apart:.2f} mm apart, distance_mm is {distance_mm:g}; an uncalibrated "
                        f"arm measures a short distance to a few mm (limit {limit:.3g} mm): {hint}",
                        path=data.source, row=first, column="socket")


def refuse_worse_than_nominal(nominal: dict, calibrated: dict, data: SocketData) -> None:
    """Refuse a fit that misses its own configurations by more than the nominal robot (RMS consistency).

    The solver starts at the nominal robot and lowers point and distance residuals together, so a
    worse point fit means the distance rows contradict the configurations: the data describe no
    robot of this structure.
    """
    before, after = nominal["consistency_rms_mm"], calibrated["consistency_rms_mm"]
    if after <= WORSE_FACTOR * before + 1e-3:
        return
    raise DataError(f"the calibrated robot misses its own configurations by more than the nominal one (consistency RMS "
                    f"{before:.3f} -> {after:.3f} mm): the socket constraints contradict each other; likely {CAUSES}, "
                    "a wrong distance_mm or fixtures whose socket distances differ; nothing written", path=data.source)
