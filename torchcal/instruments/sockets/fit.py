"""Identification from socket constraints: robot parameters and ball-centre points together.

1. Start: the nominal robot and, per group, the mean of its nominal ball centres.
   Data with no more equations (3 per configuration + 1 per distance) than unknowns are refused;
   fewer than 3 per fitted unknown warns (:mod:`torchcal.instruments.sockets.plausibility`).
2. Identifiability (:func:`torchcal.identify.identifiability.analyze`) of every candidate
   column, points preferred over the ball offset over joints from the base out. The base frame
   is never a candidate (point constraints cannot see it); what the data leave free besides
   (row 1 of the table, which only moves the fixture's unknown points; a parameter of the last
   joint equivalent to the ball offset; anything the configurations do not excite) is kept at
   nominal and named in an :class:`~torchcal.core.errors.IdentifiabilityWarning`.
3. Levenberg-Marquardt (:class:`~torchcal.identify.lm.LevenbergMarquardt`) on the base set.
4. Covariance ``s^2 (J^T J)^-1`` (:func:`torchcal.identify.uncertainty.covariance`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import torch

from torchcal.core.errors import DataError, IdentifiabilityWarning
from torchcal.identify.base import SolveResult
from torchcal.identify.compliance import GravityCompliance, gravity_torque_basis
from torchcal.identify.identifiability import IdentifiabilityReport, analyze
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.uncertainty import covariance
from torchcal.instruments.sockets.data import SocketData
from torchcal.instruments.sockets.model import SocketsProblem, group_means
from torchcal.instruments.sockets.plausibility import few_equations_warning, refuse_too_few
from torchcal.kinematics.error_model import DEFAULT_PARALLEL_THRESHOLD_DEG, ErrorModel
from torchcal.kinematics.robot import RobotModel

ROW1 = ("alpha1", "a1", "beta1", "theta1", "d1")
GAUGE_NOTE = "the base frame (a rigid motion of the robot moves every unknown point with it)"


@dataclass
class SocketsFit:
    """What a socket fit produced (SI inside).

    Attributes:
        model: error layer, ``T_reference = I`` (ball centre in ``base``).
        x: full robot parameter vector.
        points: ``(G, 3)`` fitted ball-centre point of every group, ``base`` frame, m.
        free: robot-layout indices of the estimated robot parameters.
        covariance: ``(len(free), len(free))`` covariance of those (SI units squared).
        point_sigma: ``(G, 3)`` 1-sigma of the points, m.
        sigma_residual_m: residual standard deviation per coordinate, m.
        identifiability: the analysis at the start (robot and point columns).
        solve: the solver's result.
        not_identifiable: robot parameters kept at nominal, each with what it is confounded with.
        compliance: gravity compliance identified with the geometry
            (:class:`~torchcal.identify.compliance.GravityCompliance`), if asked for.
    """

    model: ErrorModel
    x: torch.Tensor
    points: torch.Tensor
    free: torch.Tensor
    covariance: torch.Tensor
    point_sigma: torch.Tensor
    sigma_residual_m: float
    identifiability: IdentifiabilityReport
    solve: SolveResult
    not_identifiable: dict[str, list[str]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    compliance: object | None = None

    @property
    def free_names(self) -> list[str]:
        names = self.model.layout.names
        return [names[i] for i in self.free.tolist()]


def make_problem(robot: RobotModel, data: SocketData, *, distance_mm: float = 50.0, distance_weight: float = 100.0,
                 parallel_threshold_deg: float = DEFAULT_PARALLEL_THRESHOLD_DEG, gravity_points: tuple[str, ...] = (),
                 device: str | torch.device = "cpu") -> tuple[SocketsProblem, torch.Tensor]:
    """The problem with every candidate free, and its nominal start ``z0``."""
    model = ErrorModel(robot, parallel_threshold_deg=parallel_threshold_deg,
                       T_instrument_base=torch.eye(4, dtype=torch.float64), device=device)
    x0 = model.nominal_vector()
    q = data.q.to(model.device)
    c0 = group_means(model.tcp_position(q, x0), data.group, len(data.groups))
    pairs = torch.tensor([(a, b) for _, a, b in data.pairs()], dtype=torch.long).reshape(-1, 2)
    active = model.default_active()
    active[model.layout.base_slice] = False
    for name in ROW1:
        active[model.layout.index(name)] = False
    size = model.layout.size
    points = torch.arange(size, size + 3 * len(data.groups))
    basis = None
    terms = torch.zeros(0, dtype=torch.long)
    if gravity_points:
        basis = gravity_torque_basis(robot, q, tuple(gravity_points))
        start = size + 3 * len(data.groups)
        flat = basis.norm(dim=0).reshape(-1)  # a joint whose axis is along gravity has no column
        terms = start + (flat > 1e-9 * max(float(flat.max()), 1e-300)).nonzero().flatten()
    candidates = torch.cat([points, active.nonzero().flatten(), terms])
    problem = SocketsProblem(model, q, data.group.to(model.device), data.groups, pairs, distance_mm * 1e-3,
                             float(distance_weight), candidates, basis, tuple(f"gravity[{p}]" for p in gravity_points))
    z0 = torch.cat([x0, c0.reshape(-1), torch.zeros(problem.n_terms, dtype=torch.float64, device=model.device)])
    return problem, z0


def fit_sockets_data(robot: RobotModel, data: SocketData, *, distance_mm: float = 50.0, distance_weight: float = 100.0,
                     parallel_threshold_deg: float = DEFAULT_PARALLEL_THRESHOLD_DEG, max_iterations: int = 100,
                     tolerance: float = 1e-6, gravity_points: tuple[str, ...] = (), device: str | torch.device = "cpu") -> SocketsFit:
    """Identify ``robot`` from the socket constraints in ``data`` (see the module docstring)."""
    if not data.pairs():
        raise DataError("no placement has two sockets: the socket distance is the only scale, so the fit needs "
                        "at least one placement with sockets 0 and 1", path=data.source)
    problem, z0 = make_problem(robot, data, distance_mm=distance_mm, distance_weight=distance_weight,
                               parallel_threshold_deg=parallel_threshold_deg, gravity_points=gravity_points,
                               device=device)
    size = problem.n_robot
    candidates = problem.free
    n_points = 3 * problem.n_groups
    # before any solve: no more equations than unknowns leaves nothing to check and no covariance
    refuse_too_few(data, n_points, int((candidates < size).sum()), int((candidates >= size + n_points).sum()))
    _, jac = problem.jacobian(z0)
    ident = analyze(jac, problem.names, tolerance=tolerance)
    names = problem.all_names
    kept = torch.tensor(sorted(names.index(n) for n in ident.base_set), dtype=torch.long)
    dropped_points = [n for n in ident.dependent if n.startswith("point[")]
    if dropped_points:
        raise DataError(f"the configurations of {dropped_points[0].split(']')[0]}] do not locate its point "
                        "(all configurations identical?)", path=data.source)
    not_identifiable = {"base_x, base_y, base_z, base_rx, base_ry, base_rz": [GAUGE_NOTE],
                        "alpha1, a1, theta1, d1": [GAUGE_NOTE + "; row 1 places axis 1 in the base frame"]}
    not_identifiable.update({n: [p for p, _ in v[:3]] for n, v in ident.dependent.items()})
    warnings.warn(IdentifiabilityWarning(
        "kept at nominal (socket constraints cannot identify them): "
        + "; ".join(f"{n} ({', '.join(p) or 'no effect on the ball centre'})" for n, p in not_identifiable.items())),
        stacklevel=2)
    few = few_equations_warning(data, kept.numel())
    if few is not None:
        warnings.warn(few, stacklevel=2)
    problem = problem.with_free(kept)
    solve = LevenbergMarquardt(max_iterations=max_iterations).solve(problem, z0)
    r, jac = problem.jacobian(solve.x)
    cov_all, sigma = covariance(jac, r)
    is_robot = kept < size
    point_end = size + 3 * problem.n_groups
    is_point = ~is_robot & (kept < point_end)
    x, points = problem.split(solve.x)
    point_var = torch.zeros(problem.n_groups * 3, dtype=torch.float64)
    point_var[kept[is_point] - size] = cov_all[is_point][:, is_point].diagonal().cpu()
    notes = [f"socket distance {distance_mm:g} mm (weight {distance_weight:g}) on {problem.pairs.shape[0]} placement(s)"]
    if few is not None:
        notes.append(f"warning: {few}")
    compliance = None
    if gravity_points:
        compliance = GravityCompliance(tuple(gravity_points), problem.coefficients(solve.x).detach().cpu().clone())
        notes.append(f"gravity compliance at {', '.join(gravity_points)} identified with the geometry")
    return SocketsFit(
        model=problem.model, x=x.detach().clone(), points=points.detach().clone(), free=kept[is_robot],
        covariance=cov_all[is_robot][:, is_robot], point_sigma=point_var.clamp_min(0).sqrt().reshape(-1, 3),
        sigma_residual_m=sigma, identifiability=ident, solve=solve, not_identifiable=not_identifiable, notes=notes,
        compliance=compliance,
    )
