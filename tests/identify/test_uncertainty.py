"""Parameter covariance against closed forms: independent residuals, and residuals shared within regions."""

from __future__ import annotations

import numpy as np
import torch

from torchcal.identify.uncertainty import covariance


def _design(n_groups: int, per_group: int) -> tuple[torch.Tensor, np.ndarray]:
    """A straight line ``y = a + b x`` over ``n_groups`` regions of ``per_group`` poses (x grouped by region)."""
    gen = torch.Generator().manual_seed(0)
    units = np.repeat(np.arange(n_groups), per_group)
    x = torch.as_tensor(units, dtype=torch.float64) / n_groups + 0.02 * torch.randn(len(units), generator=gen,
                                                                                      dtype=torch.float64)
    return torch.stack([torch.ones_like(x), x], 1), units


def _true_covariance(jac: torch.Tensor, units: np.ndarray, noise: float, shared: float) -> torch.Tensor:
    """Sampling covariance of the least-squares estimate when residual = noise + one offset per region."""
    same = torch.as_tensor(units[:, None] == units[None, :], dtype=torch.float64)
    k = noise**2 * torch.eye(len(units), dtype=torch.float64) + shared**2 * same
    a = torch.linalg.pinv(jac)
    return a @ k @ a.T


def _average_estimate(jac, units, noise, shared, reps=150, use_units=True):
    gen = torch.Generator().manual_seed(1)
    n_groups = int(units.max()) + 1
    total = torch.zeros(2, 2, dtype=torch.float64)
    for _ in range(reps):
        offset = shared * torch.randn(n_groups, generator=gen, dtype=torch.float64)[units]
        y = offset + noise * torch.randn(len(units), generator=gen, dtype=torch.float64)
        beta = torch.linalg.lstsq(jac, y[:, None]).solution[:, 0]
        cov, _ = covariance(jac, y - jac @ beta, units if use_units else None)
        total += cov
    return total / reps


def test_independent_residuals_keep_the_classical_covariance():
    jac, units = _design(40, 10)
    truth = _true_covariance(jac, units, noise=0.01, shared=0.0)
    classical = _average_estimate(jac, units, 0.01, 0.0, use_units=False)
    widened = _average_estimate(jac, units, 0.01, 0.0)
    assert torch.allclose(classical.diagonal(), truth.diagonal(), rtol=0.05)
    # the max of two estimates can only add; with nothing shared it adds little
    assert (widened.diagonal() >= classical.diagonal() * (1 - 1e-12)).all()
    assert torch.allclose(widened.diagonal(), truth.diagonal(), rtol=0.35)


def test_residuals_shared_within_regions_widen_the_sigmas_to_the_truth():
    jac, units = _design(40, 10)
    truth = _true_covariance(jac, units, noise=0.01, shared=0.02)
    classical = _average_estimate(jac, units, 0.01, 0.02, use_units=False)
    widened = _average_estimate(jac, units, 0.01, 0.02)
    # the classical estimate misses most of the shared part (true variance several times larger)
    assert (classical.diagonal() < 0.5 * truth.diagonal()).all()
    assert torch.allclose(widened.diagonal(), truth.diagonal(), rtol=0.2)
