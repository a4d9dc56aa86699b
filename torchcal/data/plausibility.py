"""Plausibility of a measurement file against the nominal robot, before any fit or evaluation.

A file in the wrong unit parses cleanly and fits to a meaningless robot, so the size of what was
measured is compared with what the nominal robot does at the file's joints:

* joints written in radians but read as degrees (every value within +-2 pi while the robot's
  limits span far more);
* TCP points whose spread (median distance from their median point) is not the spread of the
  nominal TCP at the same joints: a factor near 1/1000 or 1000 names the likely unit and the
  option that sets it (``length_unit``);
* single points far outside anything the robot reaches (a typo such as ``1e300``).

Every finding is a :class:`~torchcal.core.errors.DataError` naming file, row and column.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchcal.core.errors import DataError
from torchcal.kinematics.robot import RobotModel

#: Measured / nominal spread outside this range is refused (a unit or robot-file mistake).
SPREAD_RATIO_RANGE = (0.2, 5.0)
#: A point farther from the others than this multiple of the robot's reach (+ 0.2 m) is refused.
OUTLIER_REACH_FACTOR = 2.0
#: Target points (a program's, a path's) all closer to the robot's base than this share of its reach:
#: metres written as mm.
METRES_AS_MM_REACH_SHARE = 0.01


def _mm(distance_m: float) -> str:
    return f"{distance_m * 1e3:.4g} mm" if math.isfinite(distance_m * 1e3) else "beyond any finite distance"


def check_joint_unit(q_file: np.ndarray, joint_unit: str, limits_rad: np.ndarray, *, path: str,
                     lines: tuple[int, ...] | list[int], advice: str = "set joint_unit=rad") -> None:
    """Refuse joints that look like radians read as degrees.

    Args:
        q_file: ``(B, N)`` joints as written in the file, in ``joint_unit``.
        limits_rad: ``(N, 2)`` joint limits, rad (infinite for a continuous joint).
        advice: what the message tells the user to do (a command without ``joint_unit`` says otherwise).
    """
    if joint_unit != "deg" or len(q_file) < 5:
        return
    largest = float(np.abs(q_file).max())
    span = limits_rad[:, 1] - limits_rad[:, 0]
    # a continuous joint (infinite limits) spans at least one turn
    widest_limit_deg = math.degrees(float(np.where(np.isfinite(span), span, 2 * math.pi).max()))
    if largest <= 2 * math.pi + 1e-6 and widest_limit_deg > 30.0:
        col = int(np.abs(q_file).max(0).argmax())
        row = int(np.abs(q_file[:, col]).argmax())
        raise DataError(
            f"every joint value lies within +-6.2832 (largest {largest:.4g}) although the robot's joints span up to "
            f"{widest_limit_deg:.0f} deg: the joints look like radians; {advice}",
            path=path, row=lines[row], column=f"q{col + 1}")


def distances_from_median(points: np.ndarray) -> np.ndarray:
    """``(B,)`` each point's distance from the points' coordinate-wise median (``points`` ``(B, 3)``):
    the size of a set of TCP points that a few wrong ones do not change."""
    with np.errstate(over="ignore", invalid="ignore"):  # a typo of 1e300 must reach the message, not warn
        return np.linalg.norm(points - np.median(points, 0), axis=1)


def length_unit_hint(ratio: float, length_unit: str, what: str, robot_name: str) -> str:
    """The likely cause of a file's lengths ``ratio`` times the nominal robot's size: metres read as
    mm (about 1e-3), mm read as metres (about 1e3), else the robot file or the file's units.
    ``what`` names the lengths (``points``, ``lengths``)."""
    if ratio < 0.01 and length_unit == "mm":
        return f"the {what} look like metres; set length_unit=m"
    if ratio > 100 and length_unit == "m":
        return f"the {what} look like millimetres; set length_unit=mm"
    return f"check the robot file ({robot_name}) and the units of the file (length_unit={length_unit})"


def check_point_spread(robot: RobotModel, q: torch.Tensor, position: torch.Tensor, length_unit: str, *, path: str,
                       lines: tuple[int, ...] | list[int]) -> None:
    """Refuse TCP points whose size does not match the nominal robot at the same joints.

    Args:
        q: ``(B, N)`` joints, rad.
        position: ``(B, 3)`` measured TCP points, m (any rigid frame).
        length_unit: the unit the file was read in (``mm`` or ``m``), for the message.
    """
    if len(q) < 5:
        return
    with torch.no_grad():
        nominal = robot.tcp_position(q.to(torch.float64)).cpu().numpy()
    measured = position.cpu().numpy()
    dist_nominal, dist_measured = distances_from_median(nominal), distances_from_median(measured)
    reach = float(dist_nominal.max())
    far = dist_measured > OUTLIER_REACH_FACTOR * reach + 0.2
    if far.any() and far.mean() < 0.5:
        k = int(np.argmax(dist_measured))
        axis = int(np.abs(measured[k] - np.median(measured, 0)).argmax())
        value = measured[k, axis] * (1e3 if length_unit == "mm" else 1.0)
        raise DataError(
            f"{value:.6g} {length_unit} puts this point {_mm(dist_measured[k])} from the others' median, while "
            f"the nominal robot's TCP stays within {reach * 1e3:.0f} mm of it at the file's joints: a typo or a wrong value",
            path=path, row=lines[k], column="xyz"[axis])
    ref, got = float(np.median(dist_nominal)), float(np.median(dist_measured))
    if ref <= 1e-6:
        return
    ratio = got / ref
    low, high = SPREAD_RATIO_RANGE
    if low <= ratio <= high:
        return
    raise DataError(
        f"the measured points spread {got * 1e3:.4g} mm around their median, the nominal robot's TCP at the same "
        f"joints {ref * 1e3:.4g} mm (ratio {ratio:.3g}): {length_unit_hint(ratio, length_unit, 'points', robot.name)}",
        path=path, column="x")


def check_targets_not_metres(points_m: torch.Tensor, reach_m: float, *, what: str, advice: str, path: str,
                             row: int | None = None) -> None:
    """Refuse target points ``(n, 3)`` (robot base frame, read as mm, m) that all lie within
    :data:`METRES_AS_MM_REACH_SHARE` of the robot's reach ``reach_m`` from the base origin: metres
    written where mm were due. ``what`` names a point (``TCP target``), ``advice`` ends the message.

    Raises:
        DataError: naming the file (and ``row``) and column ``x``.
    """
    farthest = float(points_m.norm(dim=-1).max())
    if farthest < METRES_AS_MM_REACH_SHARE * reach_m:
        raise DataError(f"every {what} lies within {farthest * 1e3:.3g} mm of the base origin, the robot reaches "
                        f"{reach_m * 1e3:.0f} mm: {advice}", path=path, row=row, column="x")
