"""Twin data for the gate tests: a grid measured in order with a drift, and a learnable error."""

from __future__ import annotations

import itertools
import math

import torch

from torchcal.data.measurements import Measurements
from torchcal.sim.twin import Twin, TwinConfig


def grid_in_measurement_order(robot) -> torch.Tensor:
    """Nested sweep, last joint innermost (4 steps of 10 deg): rows next in order are near-twins."""
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    mid, span = (lo + hi) / 2, (hi - lo) / 2

    def values(j, k):
        return (mid[j] + span[j] * torch.linspace(-0.6, 0.6, k, dtype=torch.float64)).tolist()

    axes = [values(0, 5), values(1, 3), values(2, 3), values(3, 2), values(4, 2)]
    rows = [list(c) + [float(mid[5]) + math.radians(10.0 * s)] for c in itertools.product(*axes) for s in range(4)]
    return torch.tensor(rows, dtype=torch.float64)


def drifting_series(twin: Twin, q: torch.Tensor, seed: int, generator: torch.Generator) -> Measurements:
    """Tracker readings with a drift that is a smooth random function of measurement order.

    White noise per row smoothed by a Gaussian kernel (sigma 8 rows), scaled to 0.15 mm RMS
    per axis: consecutive rows share it, rows far apart in order do not, and another series
    (another ``seed``) has another drift. Nothing about the robot.
    """
    n = len(q)
    white = torch.randn(n + 64, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    offsets = torch.arange(-32, 33, dtype=torch.float64)
    kernel = torch.exp(-0.5 * (offsets / 8.0) ** 2)
    smooth = torch.stack([torch.conv1d(white[:, k].view(1, 1, -1), kernel.view(1, 1, -1)).view(-1)[:n]
                          for k in range(3)], -1)
    drift = 0.15e-3 * smooth / smooth.pow(2).mean(0).sqrt()
    return Measurements(q=q, position=twin.measure(q, generator) + drift)


def geometric_twin() -> Twin:
    return Twin.create(TwinConfig(seed=5))


def smooth_field_series(twin: Twin, n: int, generator: torch.Generator) -> Measurements:
    """Random poses whose TCP is also displaced by a smooth, repeatable field of the joints.

    ``0.3 mm x (sin q1 cos q2, cos(q2 + q3), sin q2 sin q3)`` in ``base``: a robot property (as
    link bending would be) that no joint offset, compliance or first harmonic expresses, the
    same in every series, so a head that learns it helps on new poses.
    """
    q = twin.robot.sample_joints(n, generator, margin=math.radians(twin.config.margin_deg))
    return Measurements(q=q, position=twin.measure(q, generator) + smooth_field_instrument(twin, q))


def smooth_field_instrument(twin: Twin, q: torch.Tensor) -> torch.Tensor:
    """The field of :func:`smooth_field_series` in the instrument frame, m ``(n, 3)``."""
    field = 0.3e-3 * torch.stack([torch.sin(q[:, 0]) * torch.cos(q[:, 1]), torch.cos(q[:, 1] + q[:, 2]),
                                  torch.sin(q[:, 1]) * torch.sin(q[:, 2])], -1)
    return field @ twin.T_instrument_base()[:3, :3].T
