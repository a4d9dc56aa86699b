"""The laser-tracer length model: ranges, dead paths and the length noise model.

A laser tracer at station ``j`` measures, for reflector point ``i``, only the change of distance:
``l_ij + d_j = |P_i - S_j|`` with ``d_j`` the unknown dead path of that station set-up. Points
``P`` and stations ``S`` are in one common frame (``instrument`` frame of the multilateration, or
the robot ``base`` frame once registered), all in m.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class LengthSigma:
    """Standard deviation of one interferometric length: ``sigma(L) = constant_m + per_meter * L``.

    Attributes:
        constant_m: length-independent part, m (default 0.2 um).
        per_meter: length-proportional part, m per m (default 0.3 um/m).
    """

    constant_m: float = 0.2e-6
    per_meter: float = 0.3e-6

    def __post_init__(self) -> None:
        if not (self.constant_m >= 0.0 and self.per_meter >= 0.0 and self.constant_m + self.per_meter > 0.0):
            raise ValueError(f"LengthSigma needs non-negative terms, not both zero: {self}")

    def __call__(self, distance_m: torch.Tensor) -> torch.Tensor:
        """Sigma ``(...)`` in m of lengths whose absolute station-to-reflector distance is ``distance_m``."""
        # The length-proportional term (refractive index, laser wavelength) grows with the
        # absolute distance, not with the relative reading, so it takes |P - S|.
        return self.constant_m + self.per_meter * distance_m.abs()

    def sample(self, distance_m: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Gaussian length errors ``(...)`` in m for the given absolute distances."""
        noise = torch.randn(
            distance_m.shape, generator=generator, dtype=distance_m.dtype, device=distance_m.device
        )
        return noise * self(distance_m)


def station_distances(points_m: torch.Tensor, stations_m: torch.Tensor) -> torch.Tensor:
    """Absolute distances ``(..., n, m)`` between points ``(..., n, 3)`` and stations ``(..., m, 3)``."""
    diff = points_m.unsqueeze(-2) - stations_m.unsqueeze(-3)
    return torch.linalg.vector_norm(diff, dim=-1)


def tracer_lengths(points_m: torch.Tensor, stations_m: torch.Tensor, dead_paths_m: torch.Tensor) -> torch.Tensor:
    """Noise-free tracer readings ``l_ij = |P_i - S_j| - d_j`` ``(..., n, m)``, m."""
    return station_distances(points_m, stations_m) - dead_paths_m.unsqueeze(-2)


def stations_from_points(points_m: torch.Tensor, lengths_m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form station positions and dead paths from known points (linear least squares).

    Squaring ``|P_i - S_j| = l_ij + d_j`` gives
    ``|P_i|^2 - l_ij^2 = 2 P_i.S_j + 2 l_ij d_j + (d_j^2 - |S_j|^2)``, linear in
    ``(S_j, d_j, c_j)``: five unknowns per station, so each station needs five points that are not
    coplanar. Missing lengths (NaN) are left out.

    Args:
        points_m: ``(n, 3)`` points, m.
        lengths_m: ``(n, m)`` readings, m, NaN where missing.

    Returns:
        ``stations (m, 3)`` and ``dead_paths (m,)``, m. A starting value: it ignores the noise
        model and the constraint ``c_j = d_j^2 - |S_j|^2``.
    """
    seen = torch.isfinite(lengths_m)
    lengths = torch.where(seen, lengths_m, torch.zeros_like(lengths_m))
    w = seen.to(points_m.dtype).T.unsqueeze(-1)  # (m, n, 1)
    center = points_m.mean(0)  # conditioning: solve about the centroid
    p = points_m - center
    a = torch.cat(
        [2.0 * p.expand(lengths.shape[1], -1, -1), 2.0 * lengths.T.unsqueeze(-1), torch.ones_like(w)], -1
    )  # (m, n, 5)
    b = (p * p).sum(-1).unsqueeze(0) - lengths.T**2  # (m, n)
    sol = torch.linalg.lstsq(a * w, (b * w.squeeze(-1)).unsqueeze(-1)).solution.squeeze(-1)
    return sol[:, :3] + center, sol[:, 3]


def points_from_stations(
    stations_m: torch.Tensor, dead_paths_m: torch.Tensor, lengths_m: torch.Tensor
) -> torch.Tensor:
    """Closed-form points from known stations and dead paths (linear trilateration).

    ``|P_i|^2 - 2 P_i.S_j + |S_j|^2 = r_ij^2`` with ``r_ij = l_ij + d_j`` is linear in
    ``(P_i, |P_i|^2)``: four unknowns, so every point needs four stations that are not coplanar.

    Returns:
        ``(n, 3)`` points, m.
    """
    seen = torch.isfinite(lengths_m)
    ranges = torch.where(seen, lengths_m + dead_paths_m, torch.zeros_like(lengths_m))
    center = stations_m.mean(0)
    s = stations_m - center
    w = seen.to(stations_m.dtype).unsqueeze(-1)  # (n, m, 1)
    n = lengths_m.shape[0]
    a = torch.cat([-2.0 * s.expand(n, -1, -1), torch.ones_like(w)], -1)  # (n, m, 4)
    b = ranges**2 - (s * s).sum(-1)  # (n, m)
    sol = torch.linalg.lstsq(a * w, (b * w.squeeze(-1)).unsqueeze(-1)).solution.squeeze(-1)
    return sol[:, :3] + center
