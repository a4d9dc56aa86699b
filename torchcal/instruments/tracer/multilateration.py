"""Self-calibrating multilateration of a laser tracer moved through several stations.

Model (m, frame ``instrument``): ``l_ij + d_j = |P_i - S_j|`` for point ``i`` (one robot pose) and
station ``j``, with readings ``l_ij``, unknown points ``P_i``, stations ``S_j`` and dead paths ``d_j``:
``3n + 4m`` unknowns, of which 6 (a rigid motion of everything) no length can see.

Gauge. The solver works in the *station frame*: station ``a`` at the origin, station ``b`` on +x,
station ``c`` in the xy-plane with y > 0, where ``a < b < c`` are the three stations spanning the
largest triangle (most robust datum), and the mirror (which lengths cannot see either) is chosen so
that the points' centroid has z >= 0. Reported coordinates are in that frame, or, when
``reference_points`` (e.g. nominal robot TCP points, ``base`` frame) are given, rigidly fitted to them
(mirror included). Covariances are reported by default in the *points* gauge (inner constraints on
the points: their centroid and mean orientation carry no uncertainty), which is the shape
uncertainty a robot identifier needs once it estimates its own instrument frame; ``gauge="stations"``
gives them in the explicit station datum instead.

Solution: closed-form start (range-matrix factorization over a few dead-path hypotheses), then
Levenberg-Marquardt on the whitened residuals ``(|P_i - S_j| - d_j - l_ij) / sigma_ij`` with the
point blocks eliminated (Schur complement: the cost is ``O(n m^2)`` per step). Gross errors are
found by data snooping on externally studentized residuals and named by point and station.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Literal

import torch

from torchcal.core.errors import DataError, TorchcalError
from torchcal.instruments.tracer.lengths import LengthSigma, stations_from_points
from torchcal.instruments.tracer.start import factorize_ranges, search_dead_paths
from torchcal.kinematics.transforms import skew

_ACCEPT_RMS = 10.0  # whitened residual RMS that ends the search over start hypotheses


@dataclass(frozen=True)
class MultilaterationResult:
    """Points, stations and dead paths of a multilateration with their covariance.

    Attributes:
        points: ``(n, 3)`` reflector points, m, in the frame named by ``frame``.
        stations: ``(m, 3)`` station positions, m, same frame.
        dead_paths: ``(m,)`` dead paths, m (``|P - S| = l + d``).
        covariance: ``(3n + 4m, 3n + 4m)`` covariance, m^2, ordered
            ``[P_1xyz .. P_nxyz, S_1xyz .. S_mxyz, d_1 .. d_m]``, in the gauge named by ``gauge``.
        residuals: ``(n, m)`` model minus measured length, m, NaN where missing or rejected.
        residual_rms: RMS of the used residuals, m.
        variance_factor: a-posteriori variance of unit weight (residual chi^2 per degree of
            freedom for the sigma model used as weights); about 1 when the sigma model is right.
        dof: redundancy: used lengths minus ``(3n + 4m - 6)``.
        sigma_model: the sigma model the weights came from.
        covariance_scaled: True when ``covariance`` was scaled by ``variance_factor``.
        gauge: ``"points"`` or ``"stations"``: the datum of ``covariance``.
        frame: one line saying how the coordinate frame is fixed.
        datum_stations: indices ``(a, b, c)`` of the stations that fix the station frame.
        rejected: ``(k, 2)`` long tensor of ``(point, station)`` lengths removed as gross errors.
        iterations: LM iterations of the final solve.
        converged: whether LM met its tolerance.
    """

    points: torch.Tensor
    stations: torch.Tensor
    dead_paths: torch.Tensor
    covariance: torch.Tensor
    residuals: torch.Tensor
    residual_rms: float
    variance_factor: float
    dof: int
    sigma_model: LengthSigma
    covariance_scaled: bool
    gauge: str
    frame: str
    datum_stations: tuple[int, int, int]
    rejected: torch.Tensor
    iterations: int
    converged: bool

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_stations(self) -> int:
        return int(self.stations.shape[0])

    @property
    def point_covariances(self) -> torch.Tensor:
        """``(n, 3, 3)`` covariance block of every point, m^2."""
        n = self.n_points
        c = self.covariance[: 3 * n, : 3 * n].reshape(n, 3, n, 3)
        return c.diagonal(dim1=0, dim2=2).permute(2, 0, 1)

    @property
    def point_sigmas(self) -> torch.Tensor:
        """``(n, 3)`` standard deviation of every point coordinate, m."""
        return self.point_covariances.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()

    @property
    def point_weights(self) -> torch.Tensor:
        """``(n, 3, 3)`` inverse point covariances, 1/m^2: the weights of a point-based identifier."""
        return torch.linalg.inv(self.point_covariances)

    @property
    def station_covariances(self) -> torch.Tensor:
        """``(m, 3, 3)`` covariance block of every station, m^2."""
        n, m = self.n_points, self.n_stations
        c = self.covariance[3 * n : 3 * n + 3 * m, 3 * n : 3 * n + 3 * m].reshape(m, 3, m, 3)
        return c.diagonal(dim1=0, dim2=2).permute(2, 0, 1)

    @property
    def station_sigmas(self) -> torch.Tensor:
        """``(m, 3)`` standard deviation of every station coordinate, m."""
        return self.station_covariances.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()

    @property
    def dead_path_sigmas(self) -> torch.Tensor:
        """``(m,)`` standard deviation of every dead path, m."""
        k = 3 * self.n_points + 3 * self.n_stations
        return self.covariance.diagonal()[k:].clamp_min(0).sqrt()

    @property
    def point_rms_sigma(self) -> float:
        """Predicted RMS 3-D point error ``sqrt(trace(C_PP) / n)`` over the solved points, m (gauge dependent)."""
        var = self.point_covariances.diagonal(dim1=-2, dim2=-1).sum(-1)
        solved = torch.isfinite(var)
        return math.sqrt(float(var[solved].sum()) / max(int(solved.sum()), 1))


# ----------------------------------------------------------------------------- normal equations


@dataclass
class _Problem:
    """Whitened length problem: readings (0 where missing), mask and inverse sigmas, all ``(n, m)``."""

    lengths: torch.Tensor
    mask: torch.Tensor
    inv_sigma: torch.Tensor


def _residuals(problem: _Problem, p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Whitened residuals ``(n, m)``, 0 where missing; ``q`` is ``(m, 4)`` = ``[S_j, d_j]``."""
    rho = torch.linalg.vector_norm(p.unsqueeze(1) - q[:, :3].unsqueeze(0), dim=-1)
    return (rho - q[:, 3] - problem.lengths) * problem.inv_sigma * problem.mask


def _inv3(mat: torch.Tensor) -> torch.Tensor:
    """Inverse of a batch of 3x3 matrices by the adjugate (far cheaper than a batched LAPACK call)."""
    c0 = torch.linalg.cross(mat[..., 1, :], mat[..., 2, :])
    c1 = torch.linalg.cross(mat[..., 2, :], mat[..., 0, :])
    c2 = torch.linalg.cross(mat[..., 0, :], mat[..., 1, :])
    det = (mat[..., 0, :] * c0).sum(-1)
    return torch.stack([c0, c1, c2], -1) / det[..., None, None]


def _normal_equations(problem: _Problem, p: torch.Tensor, q: torch.Tensor):
    """Blocks of ``J^T J`` and ``J^T e`` for points (``pp``, 3x3 each) and stations (``qq``, 4x4 each)."""
    diff = p.unsqueeze(1) - q[:, :3].unsqueeze(0)
    rho = torch.linalg.vector_norm(diff, dim=-1)
    w = problem.inv_sigma * problem.mask
    e = (rho - q[:, 3] - problem.lengths) * w
    a = diff / rho.unsqueeze(-1) * w.unsqueeze(-1)  # d e_ij / d P_i, (n, m, 3)
    b = torch.cat([-a, -w.unsqueeze(-1)], -1)  # d e_ij / d (S_j, d_j), (n, m, 4)
    n, m = rho.shape
    npp = a.transpose(1, 2) @ a
    bt = b.transpose(0, 1)  # (m, n, 4)
    nqq = torch.block_diag(*(bt.transpose(1, 2) @ bt))
    npq = (a.unsqueeze(-1) * b.unsqueeze(-2)).permute(0, 2, 1, 3).reshape(n, 3, 4 * m)
    gp = (a * e.unsqueeze(-1)).sum(1)
    gq = (b * e.unsqueeze(-1)).sum(0).reshape(4 * m)
    return e, a, b, npp, nqq, npq, gp, gq


def _step(npp, nqq, npq, gp, gq, free, lam):
    """Damped Gauss-Newton step with the point blocks eliminated (Schur complement)."""
    n = npp.shape[0]
    npp_inv = _inv3(npp + lam * torch.diag_embed(npp.diagonal(dim1=-2, dim2=-1)))
    nqq_d = nqq + lam * torch.diag(nqq.diagonal())
    y = npp_inv @ npq
    yg = (npp_inv @ gp.unsqueeze(-1)).squeeze(-1)
    flat = npq.reshape(3 * n, -1)
    reduced = nqq_d - flat.T @ y.reshape(3 * n, -1)
    rhs = -(gq - flat.T @ yg.reshape(-1))
    dq = torch.zeros_like(gq)
    dq[free] = torch.linalg.solve(reduced[free][:, free], rhs[free])
    dp = -(yg + y @ dq)
    if not (torch.isfinite(dp).all() and torch.isfinite(dq).all()):
        raise RuntimeError("singular damped system")
    return dp, dq


def _levenberg_marquardt(problem, p, q, free, max_iter=200, tol=1e-12):
    """Minimize the whitened cost; returns ``(p, q, cost, iterations, converged)``."""
    cost = float((_residuals(problem, p, q) ** 2).sum())
    lam = 1e-3
    for it in range(1, max_iter + 1):
        _, _, _, npp, nqq, npq, gp, gq = _normal_equations(problem, p, q)
        while True:
            try:
                dp, dq = _step(npp, nqq, npq, gp, gq, free, lam)
            except RuntimeError:  # a damped block still singular: damp harder
                lam *= 10.0
                if lam > 1e12:
                    return p, q, cost, it, False
                continue
            p_new, q_new = p + dp, q + dq.reshape(-1, 4)
            new = float((_residuals(problem, p_new, q_new) ** 2).sum())
            if math.isfinite(new) and new <= cost:
                break
            lam *= 10.0
            if lam > 1e12:
                return p, q, cost, it, False
        step = float(torch.cat([dp.flatten(), dq]).abs().max())
        p, q = p_new, q_new
        done = cost - new <= tol * max(cost, 1e-300) or step < 1e-13
        cost, lam = new, max(lam / 10.0, 1e-12)
        if done:
            return p, q, cost, it, True
    return p, q, cost, max_iter, False


def _refine_points(problem: _Problem, p: torch.Tensor, q: torch.Tensor, iterations: int = 30) -> torch.Tensor:
    """Gauss-Newton on every point alone (stations fixed), batched; for points with missing lengths."""
    for _ in range(iterations):
        e, a, _, npp, *_ = _normal_equations(problem, p, q)
        npp = npp + 1e-9 * torch.eye(3, dtype=p.dtype, device=p.device) * npp.diagonal(dim1=-2, dim2=-1).amax(-1)[:, None, None]
        g = (a * e.unsqueeze(-1)).sum(1)
        p = p - (_inv3(npp) @ g.unsqueeze(-1)).squeeze(-1)
    return p


# ----------------------------------------------------------------------------------- gauge


def _datum_triangle(stations: torch.Tensor) -> tuple[int, int, int]:
    """Station indices ``a < b < c`` spanning the largest triangle."""
    best, area = (0, 1, 2), -1.0
    for a, b, c in itertools.combinations(range(stations.shape[0]), 3):
        s = float(torch.linalg.vector_norm(torch.linalg.cross(stations[b] - stations[a], stations[c] - stations[a])))
        if s > area:
            best, area = (a, b, c), s
    return best


def _station_frame(p: torch.Tensor, s: torch.Tensor, abc: tuple[int, int, int]):
    """Express points and stations in the station frame of ``abc`` (mirror: point centroid z >= 0)."""
    a, b, c = abc
    ex = s[b] - s[a]
    ex = ex / ex.norm()
    ey = (s[c] - s[a]) - ((s[c] - s[a]) @ ex) * ex
    ey = ey / ey.norm()
    ez = torch.linalg.cross(ex, ey)
    rot = torch.stack([ex, ey, ez])  # rows: new axes in old frame
    p_new, s_new = (p - s[a]) @ rot.T, (s - s[a]) @ rot.T
    if p_new[:, 2].mean() < 0:  # lengths cannot tell a configuration from its mirror image
        p_new[:, 2], s_new[:, 2] = -p_new[:, 2], -s_new[:, 2]
    s_new[a] = 0.0
    s_new[b, 1:] = 0.0
    s_new[c, 2] = 0.0
    return p_new, s_new


def _free_mask(m: int, abc: tuple[int, int, int], device) -> torch.Tensor:
    free = torch.ones(4 * m, dtype=torch.bool, device=device)
    a, b, c = abc
    free[[4 * a, 4 * a + 1, 4 * a + 2, 4 * b + 1, 4 * b + 2, 4 * c + 2]] = False
    return free


def _inner_constraint_transform(points: torch.Tensor, stations: torch.Tensor) -> torch.Tensor:
    """S-transform ``(N, N)`` that maps any-gauge covariance to the points' inner-constraint gauge.

    ``G`` spans the 6 rigid motions of all coordinates (``dX = t + w x X``; dead paths do not move);
    ``S = I - G (G^T E G)^-1 G^T E`` with ``E`` selecting the point coordinates.
    """
    n, m = points.shape[0], stations.shape[0]
    center = points.mean(0)
    xyz = torch.cat([points, stations]) - center
    eye = torch.eye(3, dtype=points.dtype, device=points.device).expand(n + m, 3, 3)
    g_xyz = torch.cat([eye, -skew(xyz)], -1).reshape(3 * (n + m), 6)
    g = torch.cat([g_xyz, torch.zeros(m, 6, dtype=points.dtype, device=points.device)])
    ge = g.clone()
    ge[3 * n :] = 0.0
    big_n = g.shape[0]
    return torch.eye(big_n, dtype=g.dtype, device=g.device) - g @ torch.linalg.solve(ge.T @ g, ge.T)


# ------------------------------------------------------------------------------- covariance


def _station_names(j: int) -> str:
    return f"station {j + 1} (column 'l{j + 1}')"


def _covariance_station_gauge(problem, p, q, free):
    """Unscaled full covariance in the station datum, ordered ``[P, S, d]``; plus hat-matrix diagonal."""
    e, a, b, npp, nqq, npq, _, _ = _normal_equations(problem, p, q)
    n, m = p.shape[0], q.shape[0]
    evals = torch.linalg.eigvalsh(npp)
    bad = (evals[:, 0] <= 1e-10 * evals[:, -1].clamp_min(1e-300)).nonzero().flatten()
    if bad.numel():
        i = int(bad[0])
        raise TorchcalError(
            f"point {i}: its lengths do not fix it in 3-D (seen by {int(problem.mask[i].sum())} "
            "stations, or all of them in one line); remove the pose or add stations"
        )
    npp_inv = torch.linalg.inv(npp)
    y = npp_inv @ npq
    reduced = (nqq - torch.einsum("nak,nal->kl", npq, y))[free][:, free]
    r_evals, r_evecs = torch.linalg.eigh(reduced)
    if r_evals[0] <= 1e-10 * r_evals[-1]:
        k = int(free.nonzero().flatten()[int(r_evecs[:, 0].abs().argmax())])
        what = ("x", "y", "z", "dead path")[k % 4]
        raise TorchcalError(
            f"the station geometry is singular: {_station_names(k // 4)} {what} is not determined "
            "by the lengths (stations in one plane with the points, too few points seen, or points "
            "all on a line/plane)"
        )
    cqq = torch.zeros(4 * m, 4 * m, dtype=p.dtype, device=p.device)
    idx = free.nonzero().flatten()
    cqq[idx.unsqueeze(-1), idx] = torch.linalg.inv(reduced)
    cpq = -torch.einsum("nak,kl->nal", y, cqq)
    cpp = torch.einsum("nak,kl,mbl->namb", y, cqq, y)
    cpp = cpp + torch.diag_embed(npp_inv.permute(1, 2, 0)).permute(2, 0, 3, 1)  # block diagonal
    big = torch.cat(
        [torch.cat([cpp.reshape(3 * n, 3 * n), cpq.reshape(3 * n, 4 * m)], 1),
         torch.cat([cpq.reshape(3 * n, 4 * m).T, cqq], 1)]
    )
    # hat-matrix diagonal h_ij = J_ij C J_ij^T, for the redundancy numbers 1 - h of the residuals
    cpp_blocks = cpp.diagonal(dim1=0, dim2=2).permute(2, 0, 1)  # (n, 3, 3)
    cqq_blocks = cqq.reshape(m, 4, m, 4).diagonal(dim1=0, dim2=2).permute(2, 0, 1)  # (m, 4, 4)
    cpq_blocks = cpq.reshape(n, 3, m, 4)
    hat = (
        torch.einsum("nja,nab,njb->nj", a, cpp_blocks, a)
        + 2.0 * torch.einsum("nja,najb,njb->nj", a, cpq_blocks, b)
        + torch.einsum("nja,jab,njb->nj", b, cqq_blocks, b)
    )
    order = torch.cat(
        [torch.arange(3 * n), 3 * n + torch.arange(4 * m).reshape(m, 4)[:, :3].flatten(), 3 * n + 4 * torch.arange(m) + 3]
    ).to(p.device)
    return big[order][:, order], hat, e


# ----------------------------------------------------------------------------------- checks


def _check_lengths(lengths_m: torch.Tensor, need_redundancy: bool, row_ids: list[int] | None = None) -> torch.Tensor:
    if lengths_m.ndim != 2:
        raise DataError(f"lengths must be a (points, stations) table, got shape {tuple(lengths_m.shape)}")
    n, m = lengths_m.shape
    if torch.isinf(lengths_m).any():
        i, j = (int(v) for v in torch.isinf(lengths_m).nonzero()[0])
        raise DataError(f"length is infinite at point {i}, {_station_names(j)}", row=i, column=f"l{j + 1}")
    seen = torch.isfinite(lengths_m)
    if m < 4:
        raise DataError(f"multilateration needs at least 4 stations, got {m}")
    per_station = seen.sum(0)
    for j in range(m):
        if int(per_station[j]) < 5:
            raise DataError(
                f"{_station_names(j)} saw only {int(per_station[j])} points; a station needs at least "
                "5 (4 unknowns: position and dead path, plus one to check)",
                column=f"l{j + 1}",
            )
    per_point = seen.sum(1)
    for i in range(n):
        if int(per_point[i]) < 3:
            r = i if row_ids is None else row_ids[i]
            raise DataError(
                f"point {r} was seen by only {int(per_point[i])} stations; a point needs at least 3 "
                "(remove the pose)",
                row=r,
            )
    unknowns = 3 * n + 4 * m - 6
    observed = int(seen.sum())
    if observed < unknowns + int(need_redundancy):
        raise DataError(
            f"{observed} lengths cannot determine {unknowns} unknowns (3 per point + 4 per station - 6 "
            f"for the frame) with n={n} points and m={m} stations"
            + ("; and the residual variance needs at least one more" if need_redundancy else "")
            + f": use more points (4 stations need at least {10 + int(need_redundancy)}; a point seen by "
            "only 3 stations adds no redundancy)"
        )
    return seen


def _start(problem: _Problem, lengths_m: torch.Tensor, seen: torch.Tensor, free_of):
    """LM from the closed-form start of the best dead-path candidates; the first that fits wins."""
    complete = seen.all(1)
    dof = int(seen.sum()) - (3 * seen.shape[0] + 4 * seen.shape[1] - 6)
    if int(complete.sum()) < 10:
        worst = int(seen.sum(0).argmin())
        raise DataError(
            f"only {int(complete.sum())} points were seen by every station (at least 10 are needed for "
            f"the closed-form start; {_station_names(worst)} misses most): pass initial= points"
        )
    best = None
    for dead in search_dead_paths(lengths_m[complete]):
        p_c, s, misfit = factorize_ranges(lengths_m[complete] + dead)
        if not math.isfinite(float(misfit)):
            continue
        p = p_c.mean(0).expand(lengths_m.shape[0], 3).clone()
        p[complete] = p_c
        q = torch.cat([s, dead.unsqueeze(-1)], -1)
        if not bool(complete.all()):
            p[~complete] = _refine_points(_sub(problem, ~complete), p[~complete], q)
        # a right start converges in tens of iterations; a wrong one is not worth 200
        cand = _solve_from(problem, p, q, free_of, max_iter=80)
        if cand is not None and (best is None or cand[2] < best[2]):
            best = cand
        # A wrong basin leaves residuals of mm, thousands of sigmas; one within a few sigmas of the
        # weight model is the global minimum, so the remaining candidates are not needed.
        if best is not None and best[2] <= _ACCEPT_RMS**2 * max(dof, 1):
            break
    if best is None:
        raise TorchcalError("no start found: the lengths fit no 3-D configuration (check units and columns)")
    return best


def _sub(problem: _Problem, rows: torch.Tensor) -> _Problem:
    return _Problem(problem.lengths[rows], problem.mask[rows], problem.inv_sigma[rows])


def _solve_from(problem, p, q, free_of, max_iter: int = 200):
    """Move a start into the station frame and run LM; ``(p, q, cost, iters, converged, abc)``."""
    if not (torch.isfinite(p).all() and torch.isfinite(q).all()):
        return None
    abc = _datum_triangle(q[:, :3])
    p, s = _station_frame(p, q[:, :3], abc)
    q = torch.cat([s, q[:, 3:]], -1)
    p, q, cost, its, ok = _levenberg_marquardt(problem, p, q, free_of(abc), max_iter=max_iter)
    if not math.isfinite(cost):
        return None
    return p, q, cost, its, ok, abc


# ------------------------------------------------------------------------------------ solver


def multilaterate(
    lengths_m: torch.Tensor,
    *,
    initial: torch.Tensor | tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
    sigma: LengthSigma | None = None,
    gauge: Literal["points", "stations"] = "points",
    reference_points: torch.Tensor | None = None,
    outliers: Literal["raise", "reject"] = "raise",
    outlier_threshold: float = 6.0,
    consistency_factor: float = 100.0,
) -> MultilaterationResult:
    """Points, stations and dead paths from tracer lengths (self-calibrating multilateration).

    Args:
        lengths_m: ``(n, m)`` readings ``l_ij`` in m (point ``i`` = robot pose / file row,
            station ``j`` = column ``l{j+1}``), NaN where station ``j`` did not see point ``i``.
        initial: optional start: points ``(n, 3)`` (e.g. nominal robot TCP points; stations and
            dead paths then follow in closed form), or ``(points, stations (m, 3), dead_paths (m,))``.
            ``None``: closed-form start over several dead-path hypotheses.
        sigma: length noise model. Given: it weights the lengths and the covariance is a-priori
            (``variance_factor`` tells whether the data agree). ``None``: the default
            :class:`LengthSigma` gives the relative weights and the covariance is scaled by the
            a-posteriori variance factor.
        gauge: datum of the reported covariance: ``"points"`` (inner constraints on the points) or
            ``"stations"`` (the explicit station datum of the module docstring).
        reference_points: ``(n, 3)`` points, m, to which the result is rigidly fitted (mirror
            included); the coordinates then live in their frame (e.g. the robot ``base``).
        outliers: a gross error (externally studentized residual above ``outlier_threshold``)
            raises :class:`DataError` naming the point and station (``"raise"``), or is removed and
            the solve repeated (``"reject"``).
        outlier_threshold: threshold of the studentized residuals.
        consistency_factor: raise :class:`TorchcalError` when the residual RMS exceeds this many
            sigmas of the model (the lengths fit no geometry: units, swapped columns...).

    Returns:
        :class:`MultilaterationResult`.

    Raises:
        DataError: too few stations/points/lengths, a station or point seen too rarely, a gross
            error (point and station named).
        TorchcalError: singular geometry, or lengths that fit no geometry.
    """
    lengths_m = torch.as_tensor(lengths_m, dtype=torch.float64)
    model = sigma if sigma is not None else LengthSigma()
    seen = _check_lengths(lengths_m, need_redundancy=sigma is None)
    n, m = lengths_m.shape
    dev = lengths_m.device

    def free_of(abc):
        return _free_mask(m, abc, dev)

    def problem_of(mask, dead):
        filled = torch.where(mask, lengths_m, torch.zeros_like(lengths_m))
        # Sigma needs the absolute distance, i.e. reading plus dead path; a few mm off is harmless.
        inv = 1.0 / model((filled + dead) if dead is not None else filled)
        return _Problem(filled, mask.to(lengths_m.dtype), inv * mask)

    mask = seen.clone()
    problem = problem_of(mask, None)
    if initial is None:
        p, q, _, _, _, abc = _start(problem, lengths_m, seen, free_of)
    else:
        if isinstance(initial, torch.Tensor):
            p0 = initial.to(lengths_m)
            s0, d0 = stations_from_points(p0, lengths_m)
        else:
            p0, s0, d0 = (torch.as_tensor(t).to(lengths_m) for t in initial)
        if p0.shape != (n, 3) or s0.shape != (m, 3) or d0.shape != (m,):
            raise DataError(f"initial shapes must be ({n}, 3), ({m}, 3), ({m},)")
        out = _solve_from(problem, p0, torch.cat([s0, d0.unsqueeze(-1)], -1), free_of)
        if out is None:
            raise TorchcalError("the given initial values lead to no finite solution")
        p, q, _, _, _, abc = out

    rejected: list[tuple[int, int]] = []
    rows = torch.arange(n, device=dev)  # points still in the solve (a point can be rejected whole)
    while True:
        # Re-weight with the absolute distances of the current solution, then polish.
        problem = _sub(problem_of(mask, q[:, 3]), rows)
        p, q, cost, its, ok = _levenberg_marquardt(problem, p, q, free_of(abc))
        cov, hat, e = _covariance_station_gauge(problem, p, q, free_of(abc))
        dof = int(problem.mask.sum()) - (3 * rows.numel() + 4 * m - 6)
        if dof < 2:
            break
        # Data snooping: externally studentized residuals (the suspect's own share removed from the
        # variance estimate), so one gross error stands out whatever the sigma model says.
        redundancy = (1.0 - hat).clamp_min(1e-12)
        s2_ext = ((cost - e**2 / redundancy) / (dof - 1)).clamp_min(1e-300)
        t = (e / (s2_ext * redundancy).sqrt()).abs() * problem.mask
        t = torch.where(redundancy > 1e-6, t, torch.zeros_like(t))
        worst = int(t.argmax())
        i, j = divmod(worst, m)
        t_max = float(t[i, j])
        if t_max <= outlier_threshold:
            break
        # A point seen by 4 stations has one redundant length: its residuals are then equal after
        # standardization and the data cannot tell which of its lengths is wrong, only the point.
        suspects = (t[i] >= 0.98 * t_max).nonzero().flatten().tolist()
        row = int(rows[i])
        res_um = float(e[i, j] / problem.inv_sigma[i, j]) * 1e6
        if outliers == "raise":
            if len(suspects) == 1:
                raise DataError(
                    f"gross error in the length of point {row}, {_station_names(j)}: residual "
                    f"{res_um:.1f} um, {t_max:.0f} times its standard deviation (blocked beam, lost "
                    "count, wrong station?); remove it or use outliers='reject'",
                    row=row,
                    column=f"l{j + 1}",
                )
            names = ", ".join(f"l{k + 1}" for k in suspects)
            raise DataError(
                f"gross error at point {row}: one of its lengths {names} is off by about "
                f"{t_max:.0f} standard deviations, and with this few stations seeing it the data "
                "cannot tell which; remove the pose or use outliers='reject'",
                row=row,
            )
        if len(suspects) == 1:
            rejected.append((row, j))
            mask[row, j] = False
        else:  # drop the whole point
            rejected.extend((row, k) for k in range(m) if bool(mask[row, k]))
            mask[row] = False
            keep = torch.ones(rows.numel(), dtype=torch.bool, device=dev)
            keep[i] = False
            rows, p = rows[keep], p[keep]
        reduced = torch.where(mask[rows], lengths_m[rows], torch.full_like(lengths_m[rows], torch.nan))
        _check_lengths(reduced, need_redundancy=sigma is None, row_ids=rows.tolist())

    variance_factor = cost / dof if dof > 0 else float("nan")
    if dof > 0 and math.sqrt(variance_factor) > consistency_factor:
        raise TorchcalError(
            f"the lengths fit no 3-D geometry: residual RMS is {math.sqrt(variance_factor):.0f} times "
            "the length sigma (check the length unit, the station columns, and gross errors)"
        )
    scaled = sigma is None
    if scaled:
        cov = cov * variance_factor

    s = q[:, :3]
    if gauge == "points":
        st = _inner_constraint_transform(p, s)
        cov = st @ cov @ st.T
    elif gauge != "stations":
        raise ValueError(f"gauge must be 'points' or 'stations', not {gauge!r}")
    a, b, c = abc
    frame = (
        f"station frame: station {a + 1} at the origin, station {b + 1} on +x, station {c + 1} in the "
        "xy-plane (y > 0), mirror with the points' centroid at z >= 0"
    )
    if reference_points is not None:
        ref = torch.as_tensor(reference_points).to(p)
        if ref.shape != (n, 3):
            raise DataError(f"reference_points must have shape ({n}, 3), got {tuple(ref.shape)}")
        rot, trans = _procrustes(p, ref[rows])
        p, s = p @ rot.T + trans, s @ rot.T + trans
        blocks = torch.block_diag(*([rot] * (rows.numel() + m)), torch.eye(m, dtype=p.dtype, device=dev))
        cov = blocks @ cov @ blocks.T
        frame = "rigid (mirror allowed) least-squares fit of the points to reference_points"

    e_m = torch.full_like(lengths_m, torch.nan)
    e_m[rows] = torch.where(problem.mask > 0, e / problem.inv_sigma.clamp_min(1e-300), torch.nan)
    if rows.numel() < n:  # rejected points: NaN coordinates and covariance
        p_all = torch.full((n, 3), torch.nan, dtype=p.dtype, device=dev)
        p_all[rows] = p
        idx = torch.cat([(3 * rows.unsqueeze(-1) + torch.arange(3, device=dev)).flatten(),
                         3 * n + torch.arange(4 * m, device=dev)])
        cov_all = torch.full((3 * n + 4 * m,) * 2, torch.nan, dtype=p.dtype, device=dev)
        cov_all[idx.unsqueeze(-1), idx] = cov
        p, cov = p_all, cov_all
    return MultilaterationResult(
        points=p,
        stations=s,
        dead_paths=q[:, 3],
        covariance=cov,
        residuals=e_m,
        residual_rms=float(e_m[torch.isfinite(e_m)].pow(2).mean().sqrt()),
        variance_factor=variance_factor,
        dof=dof,
        sigma_model=model,
        covariance_scaled=scaled,
        gauge=gauge,
        frame=frame,
        datum_stations=abc,
        rejected=torch.tensor(rejected, dtype=torch.long).reshape(-1, 2),
        iterations=its,
        converged=ok,
    )


def predict_covariance(
    points_m: torch.Tensor,
    stations_m: torch.Tensor,
    sigma: LengthSigma = LengthSigma(),
    visible: torch.Tensor | None = None,
    gauge: Literal["points", "stations"] = "points",
) -> tuple[torch.Tensor, tuple[int, int, int]]:
    """Covariance a multilateration would have for this geometry, before anything is measured.

    Args:
        points_m: ``(n, 3)`` planned points, m. stations_m: ``(m, 3)`` planned stations, m.
        sigma: length noise model. visible: optional ``(n, m)`` bool of lengths that will be seen.
        gauge: as in :func:`multilaterate`.

    Returns:
        The ``(3n + 4m, 3n + 4m)`` covariance (order as :class:`MultilaterationResult`), expressed
        in the frame of the given coordinates, and the datum stations of the ``"stations"`` gauge.
    """
    n, m = points_m.shape[0], stations_m.shape[0]
    seen = torch.ones(n, m, dtype=torch.bool, device=points_m.device) if visible is None else visible
    _check_lengths(torch.where(seen, 0.0, torch.nan).to(points_m), need_redundancy=False)
    abc = _datum_triangle(stations_m)
    p, s = _station_frame(points_m, stations_m, abc)
    dist = torch.linalg.vector_norm(p.unsqueeze(1) - s.unsqueeze(0), dim=-1)
    mask = seen.to(p.dtype)
    problem = _Problem(dist * mask, mask, mask / sigma(dist))  # dead paths 0: exact lengths
    q = torch.cat([s, torch.zeros(m, 1, dtype=p.dtype, device=p.device)], -1)
    cov, _, _ = _covariance_station_gauge(problem, p, q, _free_mask(m, abc, p.device))
    if gauge == "points":
        st = _inner_constraint_transform(p, s)
        cov = st @ cov @ st.T
    rot, _ = _procrustes(torch.cat([p, s]), torch.cat([points_m, stations_m]))
    blocks = torch.block_diag(*([rot] * (n + m)), torch.eye(m, dtype=p.dtype, device=p.device))
    return blocks @ cov @ blocks.T, abc


def _procrustes(source: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Orthogonal (proper or mirror) least-squares fit ``target ~ R source + t``."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    u, _, vt = torch.linalg.svd((target - mu_t).T @ (source - mu_s))
    rot = u @ vt
    return rot, mu_t - rot @ mu_s


__all__ = ["LengthSigma", "MultilaterationResult", "multilaterate", "predict_covariance"]
