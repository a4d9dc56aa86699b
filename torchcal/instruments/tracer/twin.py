"""Simulated laser-tracer length files: true TCP points seen from a few stations."""

from __future__ import annotations

import torch

from torchcal.instruments.tracer.length_model import TracerLengthModel
from torchcal.instruments.tracer.lengths import LengthSigma


def simulate_tracer_lengths(
    points_m: torch.Tensor,
    stations_m: torch.Tensor,
    dead_paths_m: torch.Tensor,
    sigma: LengthSigma = LengthSigma(),
    generator: torch.Generator | None = None,
    visibility: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """Noisy tracer readings ``l_ij = |P_i - S_j| - d_j + e_ij`` ``(n, m)``, m, NaN where not seen.

    Args:
        points_m: ``(n, 3)`` true reflector points, m (any common frame).
        stations_m: ``(m, 3)`` true tracer stations, m, same frame.
        dead_paths_m: ``(m,)`` dead paths, m.
        sigma: length noise model, ``e_ij ~ N(0, sigma(|P_i - S_j|)^2)``.
        generator: random source for the noise (and the dropped lengths).
        visibility: ``None`` (every station sees every point), an ``(n, m)`` bool mask, or a
            probability in ``[0, 1)`` that any one length is lost (beam interrupted).

    Returns:
        ``(n, m)`` lengths, m; multiply by 1000 for the ``l1..lM`` columns of a file (mm).
    """
    n, m = points_m.shape[0], stations_m.shape[0]
    if isinstance(visibility, float):
        if not 0.0 <= visibility < 1.0:
            raise ValueError(f"a loss probability must be in [0, 1), got {visibility}")
        draw = torch.rand(n, m, generator=generator, dtype=torch.float64, device=points_m.device)
        visibility = draw >= visibility
    tracer = TracerLengthModel(stations_m, dead_paths_m, sigma=sigma, visibility=visibility)
    columns = tracer.simulate(points_m, generator)
    return torch.stack(list(columns.values()), -1)
