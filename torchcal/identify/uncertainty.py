"""Parameter covariance of a least-squares fit, and the pieces of a point's prediction uncertainty.

``Cov = s^2 (J^T J)^-1`` with ``s^2 = |r|^2 / (m - p)`` the residual variance (the data's own
noise estimate), ``J`` the residual Jacobian of the ``p`` estimated parameters at the solution.
The linearization is exact to first order; it assumes independent, equal-variance residuals.

A real robot's residual is not independent: what the model cannot express (gravity it does not
model, gear errors) is a smooth function of the configuration, so neighbouring poses share it.
Given each pose's configuration region (the groups the grouped cross-validation holds out), the
cluster-robust ("sandwich") estimate ``(J^T J)^-1 (sum_g J_g^T r_g r_g^T J_g) (J^T J)^-1`` lets
residuals within a region be correlated; each parameter's sigma is then the larger of the two
estimates, with the cluster-robust correlations.
"""

from __future__ import annotations

import numpy as np
import torch


def covariance(jacobian: torch.Tensor, residuals: torch.Tensor,
               units: np.ndarray | None = None) -> tuple[torch.Tensor, float]:
    """Covariance ``(p, p)`` (parameter units squared) and residual sigma (m).

    ``units``: ``(n,)`` configuration region of each of the ``n`` poses whose residual rows
    (``m / n`` each, in pose order) make up ``residuals``; with at least 2 regions the sigmas are
    widened to the cluster-robust estimate where it is larger (see the module docstring).
    """
    m, p = jacobian.shape
    if m <= p:
        raise ValueError(f"{m} residuals cannot give a covariance for {p} parameters")
    s2 = float(residuals @ residuals) / (m - p)
    scale = jacobian.norm(dim=0).clamp_min(1e-300)
    js = jacobian / scale
    inv = torch.linalg.pinv(js.T @ js, hermitian=True)
    cov = s2 * inv
    if units is not None and len(units) and m % len(units) == 0 and len(np.unique(units)) >= 2:
        cov = _widened(cov, _cluster_robust(js, residuals, inv, np.asarray(units), m // len(units)))
    return cov / torch.outer(scale, scale), s2**0.5


def _cluster_robust(js: torch.Tensor, residuals: torch.Tensor, inv: torch.Tensor, units: np.ndarray,
                    rows: int) -> torch.Tensor:
    """CR1 sandwich covariance of the column-scaled problem (small-sample factor included)."""
    m, p = js.shape
    _, index = np.unique(np.repeat(units, rows), return_inverse=True)
    groups = int(index.max()) + 1
    sums = torch.zeros(groups, p, dtype=js.dtype, device=js.device)
    sums.index_add_(0, torch.as_tensor(index, device=js.device), js * residuals[:, None])
    factor = groups / (groups - 1) * (m - 1) / (m - p)
    return factor * inv @ (sums.T @ sums) @ inv


def _widened(classical: torch.Tensor, robust: torch.Tensor) -> torch.Tensor:
    """Sigmas ``max(classical, robust)`` per parameter, correlations of ``robust``."""
    sd_c = classical.diagonal().clamp_min(0).sqrt()
    sd_r = robust.diagonal().clamp_min(0).sqrt()
    corr = robust / torch.outer(sd_r, sd_r).clamp_min(1e-300)
    corr.diagonal().fill_(1.0)
    sd = torch.maximum(sd_c, sd_r)
    return corr * torch.outer(sd, sd)


def prediction_sigma(point_jacobian: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """Predicted 1-sigma of each TCP coordinate ``(B, 3)`` from ``d p / d x`` ``(B, 3, p)``."""
    var = torch.einsum("bip,pq,biq->bi", point_jacobian, cov, point_jacobian)
    return var.clamp_min(0.0).sqrt()


def point_covariance(point_jacobian: torch.Tensor, cov: torch.Tensor, discrepancy_var: float) -> torch.Tensor:
    """Covariance ``(B, 3, 3)`` of each predicted TCP error.

    ``point_jacobian (B, 3, K)`` and ``cov (K, K)`` propagate the parameter uncertainty;
    ``discrepancy_var`` (same units squared, per coordinate) adds what the model cannot explain
    and the measurement noise, both isotropic.
    """
    pred = torch.einsum("bip,pq,bjq->bij", point_jacobian, cov, point_jacobian)
    return pred + discrepancy_var * torch.eye(3, dtype=pred.dtype, device=pred.device)


def gaussian_radius_samples(point_cov: torch.Tensor, draws: int = 256, seed: int = 0) -> torch.Tensor:
    """``(B, draws)`` lengths of zero-mean Gaussian errors with covariances ``point_cov (B, 3, 3)``.

    The draws are the same standard normal vectors for every pose (seeded): quantiles taken from
    them are repeatable and smooth across poses.
    """
    gen = torch.Generator().manual_seed(seed)
    z = torch.randn(draws, 3, generator=gen, dtype=torch.float64).to(point_cov)
    # a symmetric square root (eigen-decomposition) also serves a singular covariance (no discrepancy,
    # parameters that do not move the point in some direction), where a Cholesky factor fails
    values, vectors = torch.linalg.eigh(0.5 * (point_cov + point_cov.transpose(-1, -2)))
    root = vectors * values.clamp_min(0).sqrt()[..., None, :]
    return torch.einsum("bij,mj->bmi", root, z).norm(dim=-1)


def conformal_factor(scores: torch.Tensor, level: float = 0.95) -> float:
    """The split-conformal quantile of non-conformity ``scores``: the ``ceil((n + 1) level)``-th smallest.

    With exchangeable calibration and test scores, a new score falls at or below it with
    probability at least ``level`` (finite-sample guarantee); with fewer than ``1 / (1 - level) - 1``
    scores the largest is returned and the guarantee does not hold.
    """
    import math

    ordered = torch.sort(scores.flatten()).values
    n = len(ordered)
    if n == 0:
        raise ValueError("no scores to calibrate on")
    k = min(n, math.ceil((n + 1) * level))
    return float(ordered[k - 1])
