"""Rows the calibrated geometry cannot explain at all: a mistyped joint angle, a point in metres.

A least-squares fit follows every row, so two bad rows of sixty spread centimetres of error over
the whole model (cross-validated 16 mm instead of 0.03 mm). Before the fit proper, a robust
geometry fit (iteratively reweighted, Cauchy weights at twice the median row error) is made on all
rows; a row whose 3-D error under it exceeds both ``ratio`` times the median row error and
``floor_mm`` is set aside. Thresholds are loose on purpose: the
largest of 1500 Gaussian errors is about 3 times their median, a mistyped angle or a unit slip is
hundreds of times it. When more than ``max_share`` of the rows look like this, the file itself is
inconsistent (two set-ups, two units) and nothing is fitted.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from torchcal.core.errors import DataError, IdentifiabilityWarning
from torchcal.data.measurements import Measurements
from torchcal.identify.calibrate import calibrate
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.robot import RobotModel

#: A row is set aside above this multiple of the median row error ...
RATIO = 10.0
#: ... and above this error (mm): real calibrated arms leave tenths of a millimetre.
FLOOR_MM = 1.0
#: More rows than this share beyond the thresholds: the file mixes set-ups or units.
MAX_SHARE = 0.2


@dataclass(frozen=True)
class OutlierRows:
    """Rows set aside: their indices in the data, file lines, errors (mm), and the median of the others."""

    index: tuple[int, ...]
    lines: tuple[int, ...]
    errors_mm: tuple[float, ...]
    median_mm: float

    def message(self, source: str) -> str:
        shown = ", ".join(f"line {line} ({e:.1f} mm)" for line, e in zip(self.lines[:8], self.errors_mm[:8]))
        more = f" and {len(self.lines) - 8} more" if len(self.lines) > 8 else ""
        return (f"{source}: {len(self.index)} row(s) miss the calibrated geometry by far more than the others "
                f"(median {self.median_mm:.3f} mm) and are left out of the fit: {shown}{more}; check their joint "
                "angles and units")


def _row_errors_mm(robot: RobotModel, data: Measurements, parallel_threshold_deg: float, *,
                   weights: torch.Tensor | None = None, use_orientation: bool = False) -> torch.Tensor:
    """3-D error (mm) of every row under a geometry fit, with per-row ``weights`` (through the
    whitening, positions only) or with the orientation rows."""
    whitening = None if weights is None else weights.sqrt()[:, None, None] * torch.eye(3, dtype=torch.float64)
    with warnings.catch_warnings():
        # a screening fit (rank cut): what the data cannot identify is the fit proper's to report,
        # with its prior; this fit's "stay at nominal" would contradict it
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        result = calibrate(robot, data, identifier=LevenbergMarquardt(max_iterations=30), use_orientation=use_orientation,
                           parallel_threshold_deg=parallel_threshold_deg, whitening=whitening)
    return (data.position - result.model.tcp_position(data.q, result.x)).norm(dim=-1) * 1e3


def _beyond(values: torch.Tensor, data: Measurements, ratio: float, floor: float):
    """The rows whose ``values`` ``(n,)`` exceed both ``ratio`` times their median and ``floor``: their indices,
    file lines, values, and the median of the other rows (``None`` where no row does)."""
    bad = (values > ratio * float(values.median())) & (values > floor)
    if not bool(bad.any()):
        return None
    index = tuple(int(i) for i in torch.nonzero(bad).squeeze(-1).tolist())
    lines = tuple(data.line_numbers[i] for i in index) if data.line_numbers else tuple(i + 2 for i in index)
    return index, lines, tuple(float(values[i]) for i in index), float(values[~bad].median())


def find_outlier_rows(robot: RobotModel, data: Measurements, *, parallel_threshold_deg: float,
                      ratio: float = RATIO, floor_mm: float = FLOOR_MM, max_share: float = MAX_SHARE,
                      rounds: int = 5) -> OutlierRows | None:
    """The rows a geometry fit cannot explain (``None``: every row is plausible).

    Raises:
        DataError: more than ``max_share`` of the rows are such rows (the file is inconsistent).
    """
    n = len(data)
    weights = torch.ones(n, dtype=torch.float64)
    for _ in range(rounds):
        # iteratively reweighted least squares with Cauchy weights: a bad row cannot pull the fit
        # towards itself and hide among the others (least squares alone smears it over the model)
        errors = _row_errors_mm(robot, data, parallel_threshold_deg, weights=weights)
        scale = 2.0 * float(errors.median())
        weights = 1.0 / (1.0 + (errors / max(scale, 1e-9)) ** 2)
    beyond = _beyond(errors, data, ratio, floor_mm)
    if beyond is None:
        return None
    found = OutlierRows(*beyond)
    index, lines = found.index, found.lines
    if len(index) > max_share * n:
        raise DataError(f"{len(index)} of {n} rows miss the calibrated geometry by more than {ratio:g}x the median "
                        f"row error ({found.median_mm:.3f} mm): the file mixes set-ups, robots or units (a share of "
                        f"rows in metres?); e.g. {', '.join(f'line {x}' for x in lines[:5])}", path=data.source)
    return found


#: With the orientation columns the position fit may lose this factor before they are taken as inconsistent.
ORIENTATION_RATIO = 3.0


def check_orientation_columns(robot: RobotModel, data: Measurements, *, parallel_threshold_deg: float,
                              ratio: float = ORIENTATION_RATIO, floor_mm: float = 0.2) -> None:
    """Refuse ``rx, ry, rz`` columns that contradict the positions.

    Two geometry fits, with and without the orientation rows: consistent columns cost the positions
    little; columns of another convention, another tool or garbage pull the model away from the
    points (``ratio`` times the position-only RMS and more than ``floor_mm``).

    Raises:
        DataError: naming both RMS and the likely causes.
    """
    if data.rotation is None:
        return
    rms = {use: float(_row_errors_mm(robot, data, parallel_threshold_deg, use_orientation=use).pow(2).mean().sqrt())
           for use in (False, True)}
    if rms[True] > ratio * rms[False] and rms[True] > floor_mm:
        raise DataError(f"the orientation columns rx, ry, rz contradict the positions: fitted with them the model "
                        f"misses the points by {rms[True]:.3f} mm RMS, without them by {rms[False]:.3f} mm; check "
                        "their convention (fixed-axis XYZ in deg, R = Rz(rz) Ry(ry) Rx(rx), tool in the instrument "
                        "frame) or remove the columns to fit positions only", path=data.source)


#: A row's orientation is set aside above this angle (deg) besides ``RATIO`` times the median: real arms
#: and probes leave hundredths to tenths of a degree, a mistyped or mis-signed angle tens of degrees.
FLOOR_DEG = 1.0


@dataclass(frozen=True)
class OrientationOutlierRows:
    """Rows whose measured orientation the calibrated geometry cannot explain: indices, file lines, angles (deg)."""

    index: tuple[int, ...]
    lines: tuple[int, ...]
    angles_deg: tuple[float, ...]
    median_deg: float

    def message(self, source: str) -> str:
        shown = ", ".join(f"line {line} ({a:.1f} deg)" for line, a in zip(self.lines[:8], self.angles_deg[:8]))
        more = f" and {len(self.lines) - 8} more" if len(self.lines) > 8 else ""
        return (f"{source}: {len(self.index)} row(s) whose orientation (rx, ry, rz) misses the calibrated geometry by far "
                f"more than the others (median {self.median_deg:.3f} deg) are left out of the fit: {shown}{more}; check "
                "their angles")


def find_orientation_outlier_rows(robot: RobotModel, data: Measurements, *, parallel_threshold_deg: float,
                                  ratio: float = RATIO, floor_deg: float = FLOOR_DEG,
                                  max_share: float = MAX_SHARE) -> OrientationOutlierRows | None:
    """The rows whose ``rx, ry, rz`` the position-fitted geometry cannot explain (``None``: all plausible, or none measured).

    The geometry is fitted to the positions (the orientation rows would follow a bad angle), the
    probe's rotation on the flange is fitted to the orientations twice (the second time without the
    rows beyond ``ratio`` times the median angle, so that a bad row cannot pull it), and a row whose
    angle then exceeds both ``ratio`` times the median and ``floor_deg`` is set aside.

    Raises:
        DataError: more than ``max_share`` of the rows are such rows (another convention or unit).
    """
    if data.rotation is None:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        result = calibrate(robot, data, identifier=LevenbergMarquardt(max_iterations=30), use_orientation=False,
                           parallel_threshold_deg=parallel_threshold_deg)
    predicted = result.model.tcp_pose(data.q, result.x)[..., :3, :3]
    measured = data.rotation.to(predicted)
    keep = torch.ones(len(data), dtype=torch.bool)
    for _ in range(2):
        probe = tf.project_to_so3((predicted[keep].transpose(-1, -2) @ measured[keep]).sum(0))
        angles = torch.rad2deg(tf.rotation_angle((predicted @ probe).transpose(-1, -2) @ measured))
        keep = angles <= ratio * float(angles.median())
    beyond = _beyond(angles, data, ratio, floor_deg)
    if beyond is None:
        return None
    found = OrientationOutlierRows(*beyond)
    index, lines = found.index, found.lines
    if len(index) > max_share * len(data):
        raise DataError(f"{len(index)} of {len(data)} rows' orientations miss the calibrated geometry by more than "
                        f"{ratio:g}x the median ({found.median_deg:.3f} deg): check the rx, ry, rz convention (fixed-axis "
                        f"XYZ in deg); e.g. {', '.join(f'line {x}' for x in lines[:5])}", path=data.source)
    return found
