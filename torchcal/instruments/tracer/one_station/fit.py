"""Identification of one length station and the robot parameters a structure allows.

Unknowns (:class:`~torchcal.instruments.tracer.joint_fit.TracerJointProblem` with one station):
``x`` (robot layout; ``T_reference = I``), the anchor ``A`` (``station1_*``, robot ``base``
frame, m) and the dead path ``d = -c`` (m): ``l = |P(q, x) - A| - d``. The gauge: a rigid motion
of the robot is absorbed by moving the anchor (``|g P - A| = |P - g^-1 A|``), so the base frame
and table row 1 are never free. Structures, simplest first:

* ``nominal``: the nominal robot; anchor, offset and the attachment point (``tool_*``) fitted;
* ``offsets``: plus the joint zero offsets ``theta2..thetaN``;
* ``full``: plus every MDH parameter the data identify.

Each structure's columns go through :func:`~torchcal.identify.identifiability.analyze` (the
attachment first, then anchor and offset, then joints from the base out); what it cannot separate
stays nominal, with an :class:`~torchcal.core.errors.IdentifiabilityWarning` naming it. Lengths
that cannot determine the anchor and offset themselves (joint configurations too few or too
alike: one configuration measured again and again) are refused, not fitted.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import torch

from torchcal.core.errors import DataError, IdentifiabilityWarning, TorchcalError
from torchcal.data.measurements import count_configurations
from torchcal.identify.base import SolveResult
from torchcal.identify.identifiability import IdentifiabilityReport, analyze
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.uncertainty import covariance
from torchcal.instruments.tracer.data import TracerData
from torchcal.instruments.tracer.joint_fit import TracerJointProblem, station_names
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


def check_station_determined(ident: IdentifiabilityReport, data: TracerData, what: str = "the anchor and offset") -> None:
    """Refuse lengths from which the analysis ``ident`` cannot determine the anchor and offset.

    A dropped ``station1_*`` / ``dead_path1`` would stay at its starting value and every parameter
    it is confounded with would absorb its effect: a made-up result with a tiny sigma.

    Raises:
        DataError: naming the file and the undetermined unknowns.
    """
    missing = [n for n in station_names(1) if n not in ident.base_set]
    if not missing:
        return
    partners = sorted({p for n in missing for p, _ in ident.dependent.get(n, [])[:2]})
    with_ = f" (confounded with {', '.join(partners)})" if partners else ""
    raise DataError(
        f"the lengths cannot determine {what}: {', '.join(missing)}{with_}; the joint configurations are too "
        "few or too alike (the same configuration measured again?): measure configurations spread over the "
        "workspace", path=data.source)


def _within_configurations(ident: IdentifiabilityReport, jac: torch.Tensor, names: list[str], data: TracerData,
                           structure: str, tolerance: float) -> tuple[IdentifiabilityReport, str]:
    """Keep no more unknowns than the distinct joint configurations less one (the residual needs it).

    Anchor, offset and attachment come first, then the robot parameters from the base out; those past
    the limit stay at nominal with an :class:`~torchcal.core.errors.IdentifiabilityWarning` (a fold of
    a small file, or ``structure=full`` on few configurations, would otherwise interpolate the
    lengths and leave no residual to give a sigma). Returns the analysis of what is kept and the
    warning's text (empty when everything fits).

    Raises:
        DataError: too few configurations even for anchor, offset and attachment.
    """
    n = count_configurations(data.q)
    if len(ident.base_set) <= n - 1:
        return ident, ""
    first = [m for m in ident.base_set if m in station_names(1) or m.startswith("tool_")]
    if len(first) > n - 1:
        raise DataError(f"{n} distinct joint configuration(s) cannot determine the {len(first)} unknowns of anchor, "
                        "offset and attachment with one to spare: measure more configurations", path=data.source)
    rest = [m for m in ident.base_set if m not in first]
    beyond = rest[n - 1 - len(first):]
    kept = [m for m in ident.base_set if m not in beyond]
    report = analyze(jac[:, [names.index(m) for m in kept]], kept, tolerance=tolerance)
    report.dependent = {**ident.dependent, **report.dependent}
    msg = (f"{n} distinct joint configurations support at most {n - 1} unknowns: {len(beyond)} parameter(s) of the "
           f"{structure} structure stay at nominal: {', '.join(beyond)}")
    warnings.warn(msg, IdentifiabilityWarning, stacklevel=3)
    return report, msg


def fit_station(robot: RobotModel, data: TracerData, structure: str = "nominal", *,
                parallel_threshold_deg: float = DEFAULT_PARALLEL_THRESHOLD_DEG, max_iterations: int = 100,
                tolerance: float = 1e-6) -> StationFit:
    """Fit anchor, offset, attachment and the robot parameters of ``structure`` to one station's lengths.

    Raises:
        DataError: the lengths cannot determine the anchor and offset (:func:`check_station_determined`).
    """
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
    check_station_determined(ident, data)
    ident, beyond = _within_configurations(ident, jac, problem.names, data, structure, tolerance)
    free = torch.tensor(sorted(problem.all_names.index(n) for n in ident.base_set), dtype=torch.long)
    problem = problem.with_free(free)
    solve = LevenbergMarquardt(max_iterations=max_iterations).solve(problem, z0)
    r, jac = problem.jacobian(solve.x)
    cov, _ = covariance(jac, r)
    x, s, d = problem.split(solve.x)
    robot_mask = free < size
    st_var = torch.zeros(4, dtype=torch.float64)
    st_var[free[~robot_mask] - size] = cov[~robot_mask][:, ~robot_mask].diagonal()
    notes = [beyond] if beyond else []
    if ident.dependent:
        notes.append("kept at nominal: " + "; ".join(
            f"{n} ({', '.join(p for p, _ in ps[:2]) or 'no effect'})" for n, ps in ident.dependent.items()))
        warnings.warn(
            f"{len(ident.dependent)} parameter(s) of the {structure} structure cannot be identified from these "
            "lengths and stay at nominal: " + "; ".join(
                f"{n} (confounded with {', '.join(p for p, _ in ps[:2]) or 'nothing'})"
                for n, ps in ident.dependent.items()), IdentifiabilityWarning, stacklevel=2)
    fit = StationFit(
        structure=structure, model=model, x=x.clone(), free=free[robot_mask], covariance=cov[robot_mask][:, robot_mask],
        anchor=s[0].clone(), offset=-float(d[0]), anchor_sigma=st_var[:3].clamp_min(0).sqrt(),
        offset_sigma=float(st_var[3].clamp_min(0).sqrt()), length_rms_m=0.0, identifiability=ident, solve=solve,
        notes=notes,
    )
    fit.length_rms_m = float((fit.predict(data.q) - data.lengths[:, 0]).pow(2).mean().sqrt())
    return fit
