"""Robot calibration directly from laser-tracer lengths (the joint method).

Unknowns: the robot's geometric parameters (MDH rows and tool point of
:class:`~torchcal.kinematics.error_model.ErrorModel`), the stations ``S_j`` and the dead paths
``d_j``. The TCP of pose ``i`` comes from the error model, so the residual of length ``l_ij`` is

    e_ij = (|P_i(x) - S_j| - d_j - l_ij) / sigma_ij          (whitened, unitless)

Gauge. A tracer has no frame of its own: lengths are unchanged by a rigid motion of robot and
stations together. The stations are therefore expressed in the robot ``base`` frame and the six
``base_*`` parameters (the instrument frame of a tracker fit) are fixed at zero with
``T_reference = I``. Row 1 of the MDH table (``alpha1, a1, theta1, d1``) moves the whole arm
rigidly (rotations about the base x and z axes, translations along them), which the stations
absorb as well: the identifiability analysis, which prefers station columns over joint columns,
finds them confounded and keeps them at nominal, as a tracker fit does with its instrument frame.

Start: stations and dead paths from the multilateration of the lengths with the nominal TCP
points as reference (so they land near the base frame), the robot at nominal. Lengths the
multilateration rejected as gross errors stay out of the joint fit.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import torch

from torchcal.core.errors import DataError, IdentifiabilityWarning, TorchcalError
from torchcal.identify.base import SolveResult
from torchcal.identify.identifiability import IdentifiabilityReport, analyze
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.uncertainty import covariance
from torchcal.instruments.tracer.data import TracerData
from torchcal.instruments.tracer.lengths import LengthSigma, station_distances, stations_from_points
from torchcal.instruments.tracer.locate import locate_poses
from torchcal.kinematics.error_model import DEFAULT_PARALLEL_THRESHOLD_DEG, ErrorModel
from torchcal.kinematics.robot import RobotModel


def station_names(m: int) -> list[str]:
    """Names of the station unknowns ``[S_1xyz .. S_mxyz, d_1 .. d_m]``."""
    xyz = [f"station{j}_{c}" for j in range(1, m + 1) for c in "xyz"]
    return xyz + [f"dead_path{j}" for j in range(1, m + 1)]


@dataclass
class TracerJointProblem:
    """Whitened length residuals as a function of ``z = [x (robot, SI), S (3m, m), d (m, m)]``.

    Duck-types :class:`~torchcal.identify.problem.CalibrationProblem` (``free``, ``names``,
    ``residuals``, ``jacobian``, ``with_free``) so every identifier solves it.

    Attributes:
        model: error layer with ``T_reference = I``: TCP in the robot ``base`` frame.
        q: ``(n, N)`` joints, rad. lengths: ``(n, m)`` readings, m (NaN where not used).
        inv_sigma: ``(n, m)`` 1/sigma of every used length, 1/m (0 where not used).
        free: indices into ``z`` of the estimated unknowns.
    """

    model: ErrorModel
    q: torch.Tensor
    lengths: torch.Tensor
    inv_sigma: torch.Tensor
    free: torch.Tensor

    @property
    def n_robot(self) -> int:
        return self.model.layout.size

    @property
    def n_stations(self) -> int:
        return int(self.lengths.shape[1])

    @property
    def all_names(self) -> list[str]:
        return list(self.model.layout.names) + station_names(self.n_stations)

    @property
    def names(self) -> list[str]:
        names = self.all_names
        return [names[i] for i in self.free.tolist()]

    @property
    def used(self) -> torch.Tensor:
        return self.inv_sigma > 0

    def split(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(x, stations (m, 3), dead_paths (m,))`` of an unknown vector."""
        p, m = self.n_robot, self.n_stations
        return z[:p], z[p : p + 3 * m].reshape(m, 3), z[p + 3 * m :]

    def residuals(self, z: torch.Tensor) -> torch.Tensor:
        """Whitened residuals ``(K,)`` of the used lengths (row-major order)."""
        x, s, d = self.split(z)
        rho = station_distances(self.model.tcp_position(self.q.to(z), x), s)
        return ((rho - d - self.lengths.nan_to_num()) * self.inv_sigma)[self.used]

    def jacobian(self, z: torch.Tensor, columns: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals ``(K,)`` and their Jacobian ``(K, len(columns))`` with respect to ``z[columns]``."""
        columns = self.free if columns is None else columns
        x, s, d = self.split(z)
        p_size, m = self.n_robot, self.n_stations
        robot_cols = columns[columns < p_size]
        pts, jac_p = self.model.position_jacobian(self.q.to(z), x, robot_cols, method="analytic")
        diff = pts.unsqueeze(1) - s.unsqueeze(0)  # (n, m, 3)
        rho = diff.norm(dim=-1)
        u = diff / rho.unsqueeze(-1)
        w = self.inv_sigma
        r = (rho - d - self.lengths.nan_to_num()) * w
        n = pts.shape[0]
        full = torch.zeros(n, m, 4 * m, dtype=z.dtype, device=z.device)
        eye = torch.arange(m, device=z.device)
        full[:, eye.unsqueeze(-1), (3 * eye).unsqueeze(-1) + torch.arange(3, device=z.device)] = -u
        full[:, eye, 3 * m + eye] = -1.0
        jac_r = torch.einsum("nmk,nkc->nmc", u, jac_p)
        station_cols = columns[columns >= p_size] - p_size
        jac = torch.cat([jac_r, full[..., station_cols]], -1) * w.unsqueeze(-1)
        # back to the order of ``columns`` (robot columns first above)
        order = torch.cat([(columns < p_size).nonzero().flatten(), (columns >= p_size).nonzero().flatten()])
        inverse = torch.empty_like(order)
        inverse[order] = torch.arange(order.numel(), device=order.device)
        used = self.used
        return r[used], jac[used][:, inverse]

    def with_free(self, free: torch.Tensor) -> TracerJointProblem:
        return TracerJointProblem(self.model, self.q, self.lengths, self.inv_sigma, free)


@dataclass
class TracerJointResult:
    """Robot, stations and dead paths fitted to the lengths (SI; ``base`` frame).

    Attributes:
        model: error layer, ``T_reference = I`` (stations in the robot ``base`` frame).
        x: robot parameter vector. free: estimated robot parameter indices.
        covariance: ``(K, K)`` covariance of the estimated robot parameters (a-posteriori scaled).
        stations: ``(m, 3)`` m. dead_paths: ``(m,)`` m. station_covariance: ``(4m, 4m)`` m^2 in
            the order ``[S_1xyz .. S_mxyz, d_1 .. d_m]`` (NaN rows for unestimated ones: none).
        variance_factor: a-posteriori variance of unit weight for the length sigma model.
        length_rms_m: RMS of the unweighted length residuals, m.
        used: ``(n, m)`` bool of the lengths in the fit. rejected: ``(k, 2)`` (pose, station)
            removed as gross errors by the multilateration.
        identifiability, solve, notes: as a tracker fit's.
    """

    model: ErrorModel
    x: torch.Tensor
    free: torch.Tensor
    covariance: torch.Tensor
    stations: torch.Tensor
    dead_paths: torch.Tensor
    station_covariance: torch.Tensor
    variance_factor: float
    length_rms_m: float
    used: torch.Tensor
    rejected: torch.Tensor
    identifiability: IdentifiabilityReport
    solve: SolveResult
    sigma_model: LengthSigma
    notes: list[str] = field(default_factory=list)

    @property
    def station_sigmas(self) -> torch.Tensor:
        m = self.stations.shape[0]
        return self.station_covariance.diagonal()[: 3 * m].clamp_min(0).sqrt().reshape(m, 3)

    @property
    def dead_path_sigmas(self) -> torch.Tensor:
        m = self.stations.shape[0]
        return self.station_covariance.diagonal()[3 * m :].clamp_min(0).sqrt()

    @property
    def free_names(self) -> list[str]:
        return [self.model.layout.names[i] for i in self.free.tolist()]


def start_stations(
    data: TracerData, nominal_points: torch.Tensor, sigma: LengthSigma | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stations ``(m, 3)`` and dead paths ``(m,)`` near the ``base`` frame, and the usable-length mask.

    Multilaterates the poses seen by at least three stations from the nominal points and fits the
    result to them (mirror included): gross errors are rejected there and left out of the mask.
    Where the located poses alone cannot be multilaterated (many poses seen by one or two
    stations), the stations follow from the nominal points by linear least squares instead.
    """
    used = data.seen.clone()
    try:
        ml, rows = locate_poses(data.lengths, nominal_points, sigma)
    except TorchcalError:
        # The joint fit can still use every length: the robot model locates the poses.
        stations, dead = stations_from_points(nominal_points, data.lengths)
        return stations, dead, used
    for i, j in ml.rejected.tolist():
        used[rows[i], j] = False
    return ml.stations, ml.dead_paths, used


def _lm(problem: TracerJointProblem, z: torch.Tensor, max_iterations: int) -> SolveResult:
    """Levenberg-Marquardt with the initial damping relative to the problem's own curvature.

    The identifier's default ``lambda_0 = 1e-6 max diag(J^T J)`` assumes a curvature of order one;
    whitened sub-micrometre lengths give ``diag(J^T J) ~ 1e12``, which would damp the first steps
    to nothing (and a near-converged restart would stop at once).
    """
    _, jac = problem.jacobian(z)
    scale = float(jac.pow(2).sum(0).max()) if jac.numel() else 1.0
    return LevenbergMarquardt(max_iterations=max_iterations, initial_damping=1e-6 / max(scale, 1e-300)).solve(problem, z)


def _base_set(problem: TracerJointProblem, z: torch.Tensor, robot_idx: torch.Tensor):
    """Identifiability at ``z``: station columns preferred over joint rows; ``(report, free, notes)``."""
    _, jac = problem.jacobian(z)
    names = problem.names
    station_first = [names[i] for i in range(len(robot_idx), len(names))] + [names[i] for i in range(len(robot_idx))]
    perm = [names.index(nm) for nm in station_first]
    report = analyze(jac[:, perm], station_first)
    notes = []
    if report.dependent:
        notes.append(
            f"{len(report.dependent)} parameter(s) cannot be identified from these lengths and stay at nominal: "
            + "; ".join(
                f"{nm} (confounded with {', '.join(p for p, _ in partners[:2]) or 'nothing'})"
                for nm, partners in report.dependent.items()
            )
        )
    all_names = problem.all_names
    free = torch.tensor(sorted(all_names.index(nm) for nm in report.base_set), dtype=torch.long)
    return report, free, notes


def calibrate_joint(
    robot: RobotModel,
    data: TracerData,
    *,
    sigma: LengthSigma = LengthSigma(),
    parallel_threshold_deg: float = DEFAULT_PARALLEL_THRESHOLD_DEG,
    max_iterations: int = 100,
    device: str | torch.device = "cpu",
) -> TracerJointResult:
    """Identify the robot, stations and dead paths from lengths alone (see module docstring).

    Args:
        robot: nominal robot (its tool is the reflector's nominal position).
        data: validated tracer session.
        sigma: length noise model: weights of the lengths; the covariance is scaled by the
            a-posteriori variance factor (robot repeatability inflates it).
        parallel_threshold_deg: Hayati switch.
        max_iterations: LM cap.
        device: where the tensors live.

    Raises:
        DataError: too few lengths for the unknowns, or lengths that fit no geometry.
    """
    data = data.to(device)
    model = ErrorModel(robot, parallel_threshold_deg=parallel_threshold_deg, device=device)
    x0 = model.nominal_vector()
    nominal_points = model.tcp_position(data.q, x0)
    s0, d0, used = start_stations(data, nominal_points, sigma)
    m = data.n_stations
    z0 = torch.cat([x0, s0.reshape(-1), d0])

    distances = station_distances(nominal_points, s0)
    inv_sigma = torch.where(used, 1.0 / sigma(distances), torch.zeros_like(distances))
    lengths = torch.where(used, data.lengths, torch.full_like(data.lengths, torch.nan))
    active = model.default_active()
    active[model.layout.base_slice] = False  # the gauge: stations live in the base frame
    n_robot = model.layout.size
    # order of preference for the base set: tool, then stations and dead paths, then joint rows
    robot_idx = active.nonzero().flatten()
    candidates = torch.cat([robot_idx, torch.arange(n_robot, n_robot + 4 * m)])
    problem = TracerJointProblem(model, data.q, lengths, inv_sigma, candidates)
    k = int(used.sum())
    if k <= len(candidates):
        raise DataError(
            f"{k} lengths cannot determine {len(candidates)} unknowns (robot parameters + 4 per station); "
            "measure more poses",
            path=data.source,
        )
    report, free, notes = _base_set(problem, z0, robot_idx)
    if k <= len(free):
        raise DataError(f"{k} lengths are too few for the {len(free)} identifiable unknowns", path=data.source)
    solve = _lm(problem.with_free(free), z0, max_iterations)
    # Analyzed at nominal, the tool is on axis 6 and alpha6, a6 look confounded with d5, theta5; an
    # off-axis tool (a few tenths of a mm) separates them by a fraction of a micrometre, which
    # sub-micrometre lengths see. So the analysis is repeated at the solution and, where it frees
    # more, the fit continues from there.
    report2, free2, notes2 = _base_set(problem, solve.x, robot_idx)
    if len(free2) > len(free) and k > len(free2):
        report, free, notes = report2, free2, notes2
        solve = _lm(problem.with_free(free), solve.x, max_iterations)
    if notes:
        warnings.warn(notes[0], IdentifiabilityWarning, stacklevel=2)
    final = problem.with_free(free)
    r, jac = final.jacobian(solve.x)
    cov, s = covariance(jac, r)
    x, stations, dead = final.split(solve.x)
    robot_mask = free < n_robot
    station_pos = free[~robot_mask] - n_robot
    station_cov = torch.full((4 * m, 4 * m), torch.nan, dtype=cov.dtype, device=cov.device)
    station_cov[station_pos.unsqueeze(-1), station_pos] = cov[~robot_mask][:, ~robot_mask]
    rho = station_distances(model.tcp_position(data.q, x), stations)
    raw = (rho - dead - data.lengths)[used]
    if s > 100.0:
        raise DataError(
            f"the lengths fit no robot: residual RMS is {s:.0f} times the length sigma after the joint fit "
            "(check the length unit, the station columns and the robot file)",
            path=data.source,
        )
    return TracerJointResult(
        model=model, x=x.clone(), free=free[robot_mask], covariance=cov[robot_mask][:, robot_mask],
        stations=stations.clone(), dead_paths=dead.clone(), station_covariance=station_cov,
        variance_factor=s**2, length_rms_m=float(raw.pow(2).mean().sqrt()), used=used, rejected=(data.seen & ~used).nonzero(),
        identifiability=report, solve=solve, sigma_model=sigma, notes=notes,
    )
