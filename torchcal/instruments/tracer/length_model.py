"""The tracer's measurement model: lengths ``l1..lM`` of points from stations, simulated and whitened."""

from __future__ import annotations

from collections.abc import Mapping

import torch

from torchcal.core.errors import DataError
from torchcal.instruments.tracer.lengths import LengthSigma, station_distances, tracer_lengths
from torchcal.instruments.tracer.multilateration import multilaterate


def length_columns(n_stations: int) -> list[str]:
    """``["l1", ..., "lM"]``: one length column per station."""
    return [f"l{j + 1}" for j in range(n_stations)]


class TracerLengthModel:
    """A laser tracer used from ``m`` stations: ``l_ij = |P_i - S_j| - d_j`` plus length noise.

    Nuisance parameters: ``[S_1xyz .. S_mxyz, d_1 .. d_m]`` (m), stations in the frame the points
    are predicted in (the robot ``base`` frame for an identifier), so no separate frame is needed.

    Args:
        stations_m: ``(m, 3)`` true stations used by :meth:`simulate`, m.
        dead_paths_m: ``(m,)`` true dead paths used by :meth:`simulate`, m.
        sigma: length noise model.
        visibility: optional ``(n, m)`` bool, which lengths :meth:`simulate` reports.
    """

    def __init__(
        self,
        stations_m: torch.Tensor,
        dead_paths_m: torch.Tensor,
        sigma: LengthSigma = LengthSigma(),
        visibility: torch.Tensor | None = None,
    ) -> None:
        self.stations_m = torch.as_tensor(stations_m, dtype=torch.float64)
        self.dead_paths_m = torch.as_tensor(dead_paths_m, dtype=torch.float64)
        if self.stations_m.ndim != 2 or self.stations_m.shape[1] != 3 or self.dead_paths_m.shape != self.stations_m.shape[:1]:
            raise ValueError("stations_m must be (m, 3) and dead_paths_m (m,)")
        self.sigma = sigma
        self.visibility = visibility

    @property
    def n_stations(self) -> int:
        return int(self.stations_m.shape[0])

    def simulate(self, true_points_m: torch.Tensor, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        s, d = self.stations_m.to(true_points_m), self.dead_paths_m.to(true_points_m)
        dist = station_distances(true_points_m, s)
        lengths = tracer_lengths(true_points_m, s, d) + self.sigma.sample(dist, generator)
        if self.visibility is not None:
            if self.visibility.shape != lengths.shape:
                raise ValueError(f"visibility must have shape {tuple(lengths.shape)}")
            lengths = torch.where(self.visibility.to(lengths.device), lengths, torch.nan)
        return dict(zip(length_columns(self.n_stations), lengths.unbind(-1)))

    def lengths(self, measured: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """``(n, m)`` length table, m, NaN where missing, from the ``l1..lM`` columns."""
        names = length_columns(self.n_stations)
        missing = [c for c in names if c not in measured]
        if missing:
            raise DataError(f"tracer data needs columns {', '.join(names)}; missing {missing[0]}", column=missing[0])
        return torch.stack([torch.as_tensor(measured[c], dtype=torch.float64) for c in names], -1)

    def initial_params(self, points_m: torch.Tensor, measured: Mapping[str, torch.Tensor]) -> torch.Tensor:
        # Multilaterate from the approximate points, then express stations in their frame: the
        # stations come out in the robot frame even though the lengths carry no frame.
        result = multilaterate(self.lengths(measured).to(points_m), initial=points_m, reference_points=points_m,
                               outliers="reject")
        return torch.cat([result.stations.reshape(-1), result.dead_paths])

    def residuals(
        self, points_m: torch.Tensor, measured: Mapping[str, torch.Tensor], params: torch.Tensor
    ) -> torch.Tensor:
        m = self.n_stations
        lengths = self.lengths(measured).to(points_m)
        s, d = params[: 3 * m].reshape(m, 3), params[3 * m : 4 * m]
        dist = station_distances(points_m, s)
        seen = torch.isfinite(lengths)
        return ((dist - d - lengths) / self.sigma(dist))[seen]
