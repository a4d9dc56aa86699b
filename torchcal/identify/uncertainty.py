"""Parameter covariance of a least-squares fit.

``Cov = s^2 (J^T J)^-1`` with ``s^2 = |r|^2 / (m - p)`` the residual variance (the data's own
noise estimate), ``J`` the residual Jacobian of the ``p`` estimated parameters at the solution.
The linearization is exact to first order; it assumes independent, equal-variance residuals.
"""

from __future__ import annotations

import torch


def covariance(jacobian: torch.Tensor, residuals: torch.Tensor) -> tuple[torch.Tensor, float]:
    """Covariance ``(p, p)`` (parameter units squared) and residual sigma (m)."""
    m, p = jacobian.shape
    if m <= p:
        raise ValueError(f"{m} residuals cannot give a covariance for {p} parameters")
    s2 = float(residuals @ residuals) / (m - p)
    scale = jacobian.norm(dim=0).clamp_min(1e-300)
    js = jacobian / scale
    inv = torch.linalg.pinv(js.T @ js, hermitian=True)
    cov = s2 * inv / torch.outer(scale, scale)
    return cov, s2**0.5


def prediction_sigma(point_jacobian: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """Predicted 1-sigma of each TCP coordinate ``(B, 3)`` from ``d p / d x`` ``(B, 3, p)``."""
    var = torch.einsum("bip,pq,biq->bi", point_jacobian, cov, point_jacobian)
    return var.clamp_min(0.0).sqrt()
