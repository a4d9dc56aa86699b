"""Planning a laser-tracer session: stations and points, and the uncertainty they will give."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.instruments.tracer.lengths import LengthSigma
from torchcal.instruments.tracer.multilateration import predict_covariance
from torchcal.kinematics.transforms import so3_exp


@dataclass(frozen=True)
class TracerPlan:
    """A proposed tracer set-up and its predicted uncertainty (points gauge, see :mod:`.tracer`).

    Attributes:
        points: ``(n, 3)`` points to visit, m. stations: ``(m, 3)`` station positions, m.
        covariance: ``(3n + 4m, 3n + 4m)`` predicted covariance, m^2 (order of
            :class:`~torchcal.instruments.tracer.multilateration.MultilaterationResult`).
        sigma_model: the length noise model of the prediction.
    """

    points: torch.Tensor
    stations: torch.Tensor
    covariance: torch.Tensor
    sigma_model: LengthSigma

    @property
    def point_covariances(self) -> torch.Tensor:
        """``(n, 3, 3)`` predicted covariance of every point, m^2."""
        n = self.points.shape[0]
        c = self.covariance[: 3 * n, : 3 * n].reshape(n, 3, n, 3)
        return c.diagonal(dim1=0, dim2=2).permute(2, 0, 1)

    @property
    def point_rms_sigma(self) -> float:
        """Predicted RMS 3-D point error after a rigid fit to the truth, m."""
        n = self.points.shape[0]
        return math.sqrt(float(self.covariance.diagonal()[: 3 * n].sum()) / n)

    @property
    def station_sigmas(self) -> torch.Tensor:
        """``(m, 3)`` predicted station coordinate sigmas, m."""
        n, m = self.points.shape[0], self.stations.shape[0]
        return self.covariance.diagonal()[3 * n : 3 * n + 3 * m].reshape(m, 3).sqrt()

    @property
    def dead_path_sigmas(self) -> torch.Tensor:
        """``(m,)`` predicted dead-path sigmas, m."""
        n, m = self.points.shape[0], self.stations.shape[0]
        return self.covariance.diagonal()[3 * n + 3 * m :].sqrt()


def _spread_directions(k: int) -> torch.Tensor:
    """``(k, 3)`` unit vectors spread over the sphere (a regular tetrahedron for 4)."""
    if k == 4:
        v = torch.tensor([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]], dtype=torch.float64)
        return v / math.sqrt(3.0)
    i = torch.arange(k, dtype=torch.float64) + 0.5  # Fibonacci sphere
    z = 1.0 - 2.0 * i / k
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = (1.0 - z**2).sqrt()
    return torch.stack([r * phi.cos(), r * phi.sin(), z], -1)


def plan_tracer_setup(
    center: torch.Tensor,
    radius: float,
    n_points: int = 60,
    n_stations: int = 4,
    generator: torch.Generator | None = None,
    sigma: LengthSigma = LengthSigma(),
    station_distance: float | None = None,
) -> TracerPlan:
    """Stations around a sphere of the working volume, random points inside it, predicted uncertainty.

    Stations sit at ``station_distance`` (default ``2.5 * radius``) from ``center`` in well-spread
    directions (a regular tetrahedron for 4 stations) with a random orientation; the points are
    uniform in the ball. The covariance comes from the Jacobian at this geometry (noise-free
    lengths), so it is known before anything is measured.

    Args:
        center: ``(3,)`` centre of the working volume, m (robot ``base`` frame).
        radius: ball radius, m.
        n_points: at least 16. n_stations: at least 4.
        generator: random source of the points and the station orientation.
        sigma: length noise model of the prediction.
        station_distance: station distance from ``center``, m.
    """
    if n_points < 16 or n_stations < 4:
        raise ValueError(f"a tracer plan needs n_points >= 16 and n_stations >= 4, got {n_points}, {n_stations}")
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}")
    center = torch.as_tensor(center, dtype=torch.float64)
    dist = 2.5 * radius if station_distance is None else float(station_distance)
    rot = so3_exp(math.pi * torch.randn(3, generator=generator, dtype=torch.float64))
    stations = center + dist * _spread_directions(n_stations) @ rot.T
    direction = torch.randn(n_points, 3, generator=generator, dtype=torch.float64)
    direction = direction / direction.norm(dim=-1, keepdim=True)
    r = radius * torch.rand(n_points, 1, generator=generator, dtype=torch.float64) ** (1.0 / 3.0)
    points = center + r * direction
    covariance, _ = predict_covariance(points, stations, sigma)
    return TracerPlan(points=points, stations=stations, covariance=covariance, sigma_model=sigma)
