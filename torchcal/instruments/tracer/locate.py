"""Multilateration of a robot's tracer session near the robot ``base`` frame, from several starts.

A robot session differs from a free multilateration in two ways: nominal TCP points are known
(good to a few mm), and beams are lost, so some poses are seen by only three stations. A point
seen by three stations has a mirror twin across the plane of those stations and no redundancy, so
a start a few mm off can end in a fold where it lies in that plane. Hence two starts: the
nominal points and, where that ends far from the noise level, the closed-form one (no guess;
needs ten poses seen by every station); the solution with the smaller residual wins. Either way the result is rigidly fitted to the nominal
points, so stations and points come out near ``base``.
"""

from __future__ import annotations

import math

import torch

from torchcal.core.errors import TorchcalError
from torchcal.instruments.tracer.lengths import LengthSigma
from torchcal.instruments.tracer.multilateration import MultilaterationResult, multilaterate

MIN_STATIONS_PER_POSE = 3  # a point located by lengths alone needs three ranges


def locate_poses(
    lengths_m: torch.Tensor, nominal_points_m: torch.Tensor, sigma: LengthSigma | None = None
) -> tuple[MultilaterationResult, torch.Tensor]:
    """The best of :func:`locate_pose_candidates` (smallest variance factor)."""
    candidates, rows = locate_pose_candidates(lengths_m, nominal_points_m, sigma, stop_variance_factor=4.0)
    return min(candidates, key=_variance_factor), rows


def _variance_factor(result: MultilaterationResult) -> float:
    return result.variance_factor if math.isfinite(result.variance_factor) else 0.0


def locate_pose_candidates(
    lengths_m: torch.Tensor,
    nominal_points_m: torch.Tensor,
    sigma: LengthSigma | None = None,
    stop_variance_factor: float | None = None,
) -> tuple[list[MultilaterationResult], torch.Tensor]:
    """Multilaterate the poses seen by at least three stations, gross errors rejected.

    Args:
        lengths_m: ``(n, m)`` readings, m, NaN where missing.
        nominal_points_m: ``(n, 3)`` nominal TCP points, ``base`` frame, m.
        sigma: length noise model (``None``: the default, covariance scaled a posteriori).
        stop_variance_factor: skip the remaining starts once a solution fits the lengths this
            well (``None``: try every start). With little redundancy a wrong geometry can fit the
            lengths as well as the right one; then only the robot model can tell them apart.

    Returns:
        The successful solutions for the located poses (their rows follow ``rows``) and
        ``rows``, the indices of the poses passed to them.

    Raises:
        TorchcalError (or DataError): from the last start when none succeeds.
    """
    seen = torch.isfinite(lengths_m)
    rows = (seen.sum(1) >= MIN_STATIONS_PER_POSE).nonzero().flatten()
    lengths, nominal = lengths_m[rows], nominal_points_m[rows]
    starts: list[torch.Tensor | None] = [nominal]
    if int(seen[rows].all(1).sum()) >= 10:
        starts.append(None)
    found: list[MultilaterationResult] = []
    error: TorchcalError | None = None
    for start in starts:
        try:
            result = multilaterate(lengths, initial=start, reference_points=nominal, sigma=sigma, outliers="reject")
        except TorchcalError as exc:
            error = exc
            continue
        found.append(result)
        if stop_variance_factor is not None and _variance_factor(result) < stop_variance_factor:
            break
    if not found:
        assert error is not None
        raise error
    return found, rows
