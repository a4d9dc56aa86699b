"""Identification of one length station and the robot parameters a structure allows.

Unknowns (:class:`~torchcal.instruments.tracer.joint_fit.TracerJointProblem` with one station):
``x`` (robot layout; ``T_reference = I``), the anchor ``A`` (``station1_*``, robot ``base``
frame, m) and the dead path ``d = -c`` (m): ``l = |P(q, x) - A| - d``. The gauge: a rigid motion
of the robot is absorbed by moving the anchor (``|g P - A| = |P - g^-1 A|``), so the base frame
and table row 1 are never free. Structures, simplest first:

* ``nominal``: the nominal robot; anchor, offset and the attachment point (``tool_*``) fitted;
* ``offsets``: plus the joint zero offsets ``theta2..thetaN``;
* ``full``: plus every MDH parameter the data identify.

Each structure's columns go through :func:`~torchcal.identify.identifiability.analyze` (anchor
and offset preferred, then the attachment, then joints from the base out); what it cannot
separate stays nominal.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from torchcal.core.errors import TorchcalError
from torchcal.identify.base import SolveResult
from torchcal.identify.identifiability import IdentifiabilityReport, analyze
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.uncertainty import covariance
from torchcal.instruments.tracer.data import TracerData
from torchcal.instruments.tracer.joint_fit import TracerJointProblem
from torchcal.instruments.tracer.lengths import station_distances, stations_from_points
from torchcal.kinematics.error_model import DEFAULT_PARALLEL_THRESHOLD_DEG, ErrorModel
from torchcal.kinematics.robot import RobotModel

STRUCTURES = ("nominal", "offsets", "full")


@dataclass
class StationFit:
    """A fitted length station (SI).

    Attributes:
        structure: which robot parameters were candidates (:data:`STRUCTURES`).
        model / x: error layer (``T_reference = I``) and robot parameter vector.
        free: robot-layout indices of the estimated robot parameters; covariance ``(K, K)`` of them.
        anchor: ``(3,)`` m, ``base`` frame. offset: ``c`` in ``l = |P - A| + c``, m.
        anchor_sigma / offset_sigma: 1-sigma, m.
        length_rms_m: RMS of the fitted length residuals.
    """

    structure: str
    model: ErrorModel
    x: torch.Tensor
    free: torch.Tensor
    covariance: torch.Tensor
    anchor: torch.Tensor
    offset: float
    anchor_sigma: torch.Tensor
    offset_sigma: float
    length_rms_m: float
    identifiability: IdentifiabilityReport
    solve: SolveResult
    notes: list[str] = field(default_factory=list)

    def predict(self, q: torch.Tensor) -> torch.Tensor:
        """Predicted lengths ``(n,)`` m at joints ``q (n, N)`` rad."""
        points = self.model.tcp_position(q.to(self.x), self.x)
        return station_distances(points, self.anchor.unsqueeze(0))[:, 0] + self.offset


def candidate_columns(model: ErrorModel, structure: str) -> torch.Tensor:
    """Robot-layout indices that ``structure`` lets the fit estimate (before identifiability)."""
    if structure not in STRUCTURES:
        raise TorchcalError(f"unknown length-station structure {structure!r}; choose one of {', '.join(STRUCTURES)}")
    layout = model.layout
    tool = [layout.index(f"tool_{c}") for c in "xyz"]
    if structure == "nominal":
        return torch.tensor(tool)
    if structure == "offsets":
        return torch.tensor(tool + [layout.index(f"theta{i}") for i in range(2, model.robot.dof + 1)])
    active = model.default_active()
    active[layout.base_slice] = False
    for name in ("alpha1", "a1", "beta1", "theta1", "d1"):
        active[layout.index(name)] = False
    return active.nonzero().flatten()


def fit_station(robot: RobotModel, data: TracerData, structure: str = "nominal", *,
                parallel_threshold_deg: float = DEFAULT_PARALLEL_THRESHOLD_DEG, max_iterations: int = 100,
                tolerance: float = 1e-6) -> StationFit:
    """Fit anchor, offset, attachment and the robot parameters of ``structure`` to one station's lengths."""
    if data.n_stations != 1:
        raise TorchcalError(f"a length station has one length column, got {data.n_stations}")
    model = ErrorModel(robot, parallel_threshold_deg=parallel_threshold_deg,
                       T_instrument_base=torch.eye(4, dtype=torch.float64))
    x0 = model.nominal_vector()
    size = model.layout.size
    s0, d0 = stations_from_points(model.tcp_position(data.q, x0), data.lengths)
    z0 = torch.cat([x0, s0.reshape(-1), d0])
    robot_cols = candidate_columns(model, structure)
    station = torch.arange(size, size + 4)
    inv_sigma = torch.full_like(data.lengths, 1e3)  # residuals in mm: the LM is scale-free, sigma comes a posteriori
    problem = TracerJointProblem(model, data.q, data.lengths, inv_sigma, torch.cat([station, robot_cols]))
    _, jac = problem.jacobian(z0)
    ident = analyze(jac, problem.names, tolerance=tolerance)
    free = torch.tensor(sorted(problem.all_names.index(n) for n in ident.base_set), dtype=torch.long)
    problem = problem.with_free(free)
    solve = LevenbergMarquardt(max_iterations=max_iterations).solve(problem, z0)
    r, jac = problem.jacobian(solve.x)
    cov, _ = covariance(jac, r)
    x, s, d = problem.split(solve.x)
    robot_mask = free < size
    st_var = torch.zeros(4, dtype=torch.float64)
    st_var[free[~robot_mask] - size] = cov[~robot_mask][:, ~robot_mask].diagonal()
    notes = []
    if ident.dependent:
        notes.append("kept at nominal: " + "; ".join(
            f"{n} ({', '.join(p for p, _ in ps[:2]) or 'no effect'})" for n, ps in ident.dependent.items()))
    fit = StationFit(
        structure=structure, model=model, x=x.clone(), free=free[robot_mask], covariance=cov[robot_mask][:, robot_mask],
        anchor=s[0].clone(), offset=-float(d[0]), anchor_sigma=st_var[:3].clamp_min(0).sqrt(),
        offset_sigma=float(st_var[3].clamp_min(0).sqrt()), length_rms_m=0.0, identifiability=ident, solve=solve,
        notes=notes,
    )
    fit.length_rms_m = float((fit.predict(data.q) - data.lengths[:, 0]).pow(2).mean().sqrt())
    return fit
