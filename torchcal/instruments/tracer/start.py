"""Closed-form starting values for multilateration, with no user guess.

With the dead paths guessed, the ranges ``r_ij = l_ij + d_j`` are known and the positions follow
from a factorization of the squared-range matrix (time-of-arrival self-calibration): double
centering ``B = -1/2 J_n D J_m`` of ``D_ij = r_ij^2`` gives ``B = P~ S~^T`` (rank 3, points and
stations about their centroids), known up to an invertible ``A``: ``P~ = U A``. The row means of
``D`` are linear in ``Q = A A^T`` and ``w = A t`` (``t`` the station centroid), so ten or more
points seen by every station fix ``A`` up to a rotation, which is the gauge.

The dead paths are not known, and with four stations the squared-range matrix has no rank
condition that would give them. They are searched instead: every candidate is factorized (batched,
thousands at once) and scored by how well its configuration reproduces its own ranges; a coarse
grid of station distances is refined by a shrinking pattern search.
"""

from __future__ import annotations

import torch


def factorize_ranges(ranges_m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Points ``(..., n, 3)`` and stations ``(..., m, 3)`` from complete ranges ``(..., n, m)``, m.

    Batched over leading dims. The frame has the point centroid at the origin and an arbitrary
    orientation and handedness. Also returns the RMS misfit ``(...,)`` between the configuration's
    distances and the ranges (m), the score of a dead-path guess (``inf`` where no real
    configuration exists).
    """
    d2 = ranges_m**2
    rows, cols = d2.mean(-1, keepdim=True), d2.mean(-2, keepdim=True)
    b = -0.5 * (d2 - rows - cols + d2.mean((-2, -1), keepdim=True))
    u, sv, vh = torch.linalg.svd(b, full_matrices=False)
    u3, s3, v3 = u[..., :3], sv[..., :3], vh[..., :3, :].transpose(-1, -2)
    # y_i = u_i^T Q u_i - mean_k(u_k^T Q u_k) - 2 u_i^T w: linear in the 6 entries of Q and in w
    y = (rows - rows.mean(-2, keepdim=True)).squeeze(-1)
    iu = torch.triu_indices(3, 3, device=ranges_m.device)
    two = torch.where(iu[0] == iu[1], 1.0, 2.0).to(u3)
    quad = u3[..., iu[0]] * u3[..., iu[1]] * two
    quad = quad - quad.mean(-2, keepdim=True)
    design = torch.cat([quad, -2.0 * u3], -1)  # (..., n, 9)
    gram = design.transpose(-1, -2) @ design
    gram = gram + 1e-12 * gram.diagonal(dim1=-2, dim2=-1).amax(-1)[..., None, None] * torch.eye(9, dtype=u3.dtype, device=u3.device)
    sol = torch.linalg.solve(gram, (design.transpose(-1, -2) @ y.unsqueeze(-1))).squeeze(-1)
    q = torch.zeros(*sol.shape[:-1], 3, 3, dtype=u3.dtype, device=u3.device)
    q[..., iu[0], iu[1]] = sol[..., :6]
    q = q + q.transpose(-1, -2) - torch.diag_embed(q.diagonal(dim1=-2, dim2=-1))
    evals, evecs = torch.linalg.eigh(q)
    # A Q with a negative eigenvalue comes from a wrong dead-path guess; clamping keeps a usable
    # (if distorted) configuration whose misfit then scores the guess.
    top = evals[..., -1:].clamp_min(1e-300)
    a = evecs * evals.clamp_min(1e-6 * top).sqrt().unsqueeze(-2)  # Q = a a^T
    a_inv = evecs.transpose(-1, -2) / evals.clamp_min(1e-6 * top).sqrt().unsqueeze(-1)
    t = (a_inv @ sol[..., 6:].unsqueeze(-1)).squeeze(-1)  # w = a t
    points = u3 @ a
    stations = (v3 * s3.unsqueeze(-2)) @ a_inv.transpose(-1, -2) + t.unsqueeze(-2)
    dist = torch.linalg.vector_norm(points.unsqueeze(-2) - stations.unsqueeze(-3), dim=-1)
    misfit = (dist - ranges_m).pow(2).mean((-2, -1)).sqrt()
    valid = (evals[..., -1] > 0) & (s3[..., 2] > 1e-9 * s3[..., 0]) & torch.isfinite(misfit)
    return points, stations, torch.where(valid, misfit, torch.full_like(misfit, torch.inf))


def search_dead_paths(
    lengths_m: torch.Tensor,
    *,
    n_best: int = 3,
    grid: tuple[float, ...] = (0.6, 1.0, 1.6, 2.6, 4.2, 6.8),
    iterations: int = 60,
) -> torch.Tensor:
    """Dead-path candidates ``(k, m)``, best first, for complete lengths ``(n, m)`` (m).

    Station ``j`` at distance ``D_j`` from the middle of the points has ``d_j ~ D_j - median_i l_ij``;
    ``D_j`` runs over ``grid`` times the largest spread of one station's readings (at most the
    point-cloud diameter). The ``n_best`` best grid points (by factorization misfit) are refined by
    Levenberg-Marquardt on the misfit residuals over the ``m`` dead paths (finite-difference
    Jacobian, all candidates in one batch): the misfit has a long, flat valley (all dead paths and
    station distances growing together) that a pattern search crawls along.
    """
    m = lengths_m.shape[-1]
    spread = (lengths_m.amax(0) - lengths_m.amin(0)).max()
    middle = lengths_m.median(0).values
    levels = torch.tensor(grid, dtype=lengths_m.dtype, device=lengths_m.device) * spread
    if len(grid) ** m <= 20000:
        combos = torch.cartesian_prod(*([levels] * m))
    else:  # many stations: one common distance for all
        combos = levels.unsqueeze(-1).expand(-1, m)
    candidates = combos - middle
    score = torch.cat([_misfit(lengths_m, part)[1] for part in candidates.split(4096)])
    best = candidates[score.argsort()[:n_best]]
    best = _refine(lengths_m, best, iterations, 1e-7 * float(spread))
    return best[_misfit(lengths_m, best)[1].argsort()]


def _misfit(lengths_m: torch.Tensor, dead_paths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals ``(k, n*m)`` and RMS ``(k,)`` of the factorization for dead paths ``(k, m)``."""
    ranges = lengths_m.unsqueeze(0) + dead_paths.unsqueeze(-2)
    points, stations, rms = factorize_ranges(ranges)
    dist = torch.linalg.vector_norm(points.unsqueeze(-2) - stations.unsqueeze(-3), dim=-1)
    return (dist - ranges).flatten(-2), rms


def _refine(lengths_m: torch.Tensor, dead: torch.Tensor, iterations: int, h: float) -> torch.Tensor:
    """Batched LM over the dead paths on the factorization misfit."""
    k, m = dead.shape
    eye = torch.eye(m, dtype=dead.dtype, device=dead.device)
    lam = torch.full((k,), 1e-3, dtype=dead.dtype, device=dead.device)
    res, rms = _misfit(lengths_m, dead)
    cost = torch.where(torch.isfinite(rms), (res**2).sum(-1), torch.full_like(rms, torch.inf))
    for _ in range(iterations):
        shifted = dead.unsqueeze(1) + h * eye  # (k, m, m)
        res_h, _ = _misfit(lengths_m, shifted.reshape(-1, m))
        jac = (res_h.reshape(k, m, -1) - res.unsqueeze(1)) / h  # (k, m, n*m)
        jtj = jac @ jac.transpose(-1, -2)
        g = (jac @ res.unsqueeze(-1)).squeeze(-1)
        jtj = jtj + lam[:, None, None] * torch.diag_embed(jtj.diagonal(dim1=-2, dim2=-1))
        step = -torch.linalg.solve(jtj + 1e-30 * eye, g.unsqueeze(-1)).squeeze(-1)
        trial = dead + step
        res_t, rms_t = _misfit(lengths_m, trial)
        cost_t = torch.where(torch.isfinite(rms_t), (res_t**2).sum(-1), torch.full_like(rms_t, torch.inf))
        better = cost_t < cost
        dead = torch.where(better.unsqueeze(-1), trial, dead)
        res = torch.where(better.unsqueeze(-1), res_t, res)
        gain = (cost_t - cost).abs() / cost.clamp_min(1e-300)
        lam = torch.where(better, (lam / 5.0).clamp_min(1e-9), lam * 10.0)
        cost = torch.where(better, cost_t, cost)
        # done when every candidate is stuck (damping exhausted) or no longer improving
        if bool(((lam > 1e8) | (better & (gain < 1e-9))).all()):
            break
    return dead
