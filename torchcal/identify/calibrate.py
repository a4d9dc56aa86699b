"""Geometric calibration end to end: register, analyze, solve, quantify.

1. Closed-form rigid registration of the nominal TCP positions (``base``) onto the measured ones
   (``instrument``) gives the reference ``T_instrument_base``: no user guess.
2. Identifiability analysis at the start: non-identifiable parameters are named, warned about
   and fixed at nominal (a base parameter set is estimated, nothing is silently absorbed).
3. The chosen identifier (LM by default) estimates the base set.
4. Covariance and 1-sigma of every estimated parameter from the residual variance.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from torchcal.core.errors import DataError, IdentifiabilityWarning
from torchcal.data.measurements import Measurements
from torchcal.identify.base import Identifier, SolveResult
from torchcal.identify.identifiability import IdentifiabilityReport, analyze
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.prior import Prior, PriorSpec, solve_map
from torchcal.identify.problem import CalibrationProblem
from torchcal.identify.uncertainty import covariance
from torchcal.kinematics.error_model import DEFAULT_PARALLEL_THRESHOLD_DEG, ErrorModel
from torchcal.kinematics.robot import RobotModel
from torchcal.kinematics.transforms import rigid_registration


@dataclass
class CalibrationResult:
    """Everything a geometric fit produced (SI units inside).

    Attributes:
        model: the error layer, its ``T_reference`` holding the fitted instrument frame.
        x: full parameter vector (base correction folded into ``model.T_reference``).
        free: indices of estimated parameters (the base set).
        covariance: ``(K, K)`` of the estimated parameters.
        sigma_residual_m: residual standard deviation per coordinate.
        identifiability: the analysis at the start.
        solve: the solver's own result (iterations, history...).
        compliance: gravity compliance identified with the geometry
            (:class:`~torchcal.identify.compliance.GravityCompliance`), if any.
        harmonics: first-harmonic joint errors identified with the geometry
            (:class:`~torchcal.identify.harmonics.JointHarmonics`), if any.
        prior: the prior of a MAP fit (:mod:`torchcal.identify.prior`); ``None`` for the rank-cut fit.
        noise_sigma_m: the data's noise sigma per coordinate the MAP fit weighted them with.
        prior_selection: how the prior's scale was chosen (the evidence or cross-validation table), if it was.
        log_evidence: the MAP fit's log marginal likelihood (:func:`~torchcal.identify.prior.log_evidence`).
        joint_covariance: where joint-space terms were identified with the geometry, the joint fit's
            covariance of the estimated geometry parameters (``free``, in that order) followed by the
            terms' coefficients; ``joint_coefficients`` ``(K, 2)`` gives each coefficient's (row,
            joint) (:meth:`~torchcal.identify.joint_errors.JointSpaceErrors.shifted`). ``covariance``
            is its geometry block.
    """

    model: ErrorModel
    x: torch.Tensor
    free: torch.Tensor
    covariance: torch.Tensor
    sigma_residual_m: float
    identifiability: IdentifiabilityReport
    solve: SolveResult
    method: str = "lm"
    notes: list[str] = field(default_factory=list)
    compliance: object | None = None
    harmonics: object | None = None
    prior: Prior | None = None
    noise_sigma_m: float | None = None
    prior_selection: dict | None = None
    log_evidence: float | None = None
    joint_covariance: torch.Tensor | None = None
    joint_coefficients: torch.Tensor | None = None

    @property
    def free_names(self) -> list[str]:
        names = self.model.layout.names
        return [names[i] for i in self.free.tolist()]

    def parameter_sigma(self) -> torch.Tensor:
        return self.covariance.diagonal().clamp_min(0).sqrt()


def register_instrument(robot: RobotModel, data: Measurements, model: ErrorModel | None = None, x: torch.Tensor | None = None) -> torch.Tensor:
    """Closed-form ``T_instrument_base`` from predicted (``base``) to measured (``instrument``) TCP."""
    if model is None or x is None:
        predicted = robot.tcp_position(data.q)
    else:
        base_model = ErrorModel(model.robot, T_instrument_base=torch.eye(4, dtype=torch.float64))
        x_base = x.clone()
        x_base[model.layout.base_slice] = 0.0
        predicted = base_model.tcp_position(data.q, x_base)
    return rigid_registration(predicted, data.position)


def calibrate(
    robot: RobotModel,
    data: Measurements,
    *,
    identifier: Identifier | None = None,
    use_orientation: bool | None = None,
    parallel_threshold_deg: float = DEFAULT_PARALLEL_THRESHOLD_DEG,
    fixed: tuple[str, ...] = (),
    register: bool = True,
    device: str | torch.device = "cpu",
    whitening: torch.Tensor | None = None,
    units: np.ndarray | None = None,
    prior: PriorSpec | None = None,
    start: CalibrationResult | None = None,
) -> CalibrationResult:
    """Identify the geometric parameters of ``robot`` from position (and orientation) data.

    Args:
        identifier: solver (default: Levenberg-Marquardt).
        use_orientation: fit orientation too (default: when the data has it).
        fixed: parameter names to keep at nominal in addition to the non-identifiable ones.
        register: find the instrument frame by closed-form registration (otherwise the data
            is taken to be in the ``base`` frame, and the base correction is still fitted).
        whitening: optional ``(n, 3, 3)`` per-pose whitening of the position residuals (see
            :class:`CalibrationProblem`); ``sigma_residual_m`` is then the unitless a-posteriori
            sigma of unit weight.
        units: ``(n,)`` configuration region of each pose: the covariance then also allows
            residuals correlated within a region (:func:`~torchcal.identify.uncertainty.covariance`).
        prior: MAP identification with this prior (:mod:`torchcal.identify.prior`): every parameter
            is estimated, the rank analysis is a diagnostic and what the data cannot see stays at
            the prior. ``None``: the rank cut (non-identifiable parameters fixed at nominal).
        start: a MAP fit of the same robot and layout to start from (its instrument frame,
            parameters and noise sigma; e.g. the fit on all poses for a fold's fit, or the next
            tighter prior): only the iterations change, the prior and the minimum do not.
    """
    identifier = identifier or LevenbergMarquardt()
    use_orientation = data.rotation is not None if use_orientation is None else use_orientation
    if whitening is not None and use_orientation:
        raise DataError("whitening applies to position-only fits", path=data.source)
    if use_orientation and data.rotation is None:
        raise DataError("orientation fit requested but the file has no rx, ry, rz columns", path=data.source)
    data = data.to(device)
    warm = start is not None and prior is not None and start.prior is not None
    if warm:
        assert start is not None
        reference = start.model.T_reference.to(device)
    else:
        reference = register_instrument(robot, data) if register else torch.eye(4, dtype=torch.float64)
    model = ErrorModel(
        robot, with_orientation=use_orientation, parallel_threshold_deg=parallel_threshold_deg,
        T_instrument_base=reference, device=device,
    )
    x0 = model.nominal_vector()
    active = model.default_active()
    for name in fixed:
        if name not in model.layout.names:
            raise DataError(f"cannot fix unknown parameter '{name}'; known: {', '.join(model.layout.names)}")
        active[model.layout.index(name)] = False
    if prior is not None and prior.nominal:
        active[model.layout.table_slice] = False
    candidates = torch.nonzero(active).squeeze(-1)
    problem = CalibrationProblem(
        model, data, candidates, use_orientation=use_orientation,
        whitening=None if whitening is None else whitening.to(device),
    )
    rows = problem.rows_per_pose * len(data)
    if prior is not None:
        return _calibrate_map(model, problem, prior, identifier, units, data, start if warm else None)
    if rows <= len(candidates):
        raise DataError(
            f"{len(data)} poses give {rows} equations ({problem.rows_per_pose} per pose"
            + (", positions only" if problem.rows_per_pose == 3 and data.rotation is not None else "")
            + f"), no more than the {len(candidates)} parameters to identify; measure at least "
            f"{len(candidates) // problem.rows_per_pose + 1} poses (3-4x that is advisable)",
            path=data.source,
        )
    _, jac0 = problem.jacobian(x0)
    report = analyze(jac0, problem.names)
    notes = []
    if report.dependent:
        msg = (
            f"{len(report.dependent)} parameter(s) cannot be identified from these data and stay at nominal: "
            + "; ".join(
                f"{n} (confounded with {', '.join(p for p, _ in partners[:2]) or 'nothing'})"
                for n, partners in report.dependent.items()
            )
        )
        notes.append(msg)
        warnings.warn(msg, IdentifiabilityWarning, stacklevel=2)
    names = model.layout.names
    free = torch.tensor(sorted(names.index(n) for n in report.base_set), dtype=torch.long)
    if rows <= len(free):
        raise DataError(f"{len(data)} poses are too few for the {len(free)} identifiable parameters", path=data.source)
    result = identifier.solve(problem.with_free(free), x0)
    final_free = torch.tensor(sorted(names.index(n) for n in result.selected), dtype=torch.long)
    final_problem = problem.with_free(final_free)
    r, jac = final_problem.jacobian(result.x)
    cov, sigma = covariance(jac, r, units)
    reference, x = model.recentered(result.x)
    model.T_reference = reference
    return CalibrationResult(
        model=model, x=x, free=final_free, covariance=cov, sigma_residual_m=sigma,
        identifiability=report, solve=result, method=identifier.name, notes=notes,
    )


def _calibrate_map(model: ErrorModel, problem: CalibrationProblem, spec: PriorSpec, identifier: Identifier,
                   units: np.ndarray | None, data: Measurements, start: CalibrationResult | None = None) -> CalibrationResult:
    """MAP identification of every candidate parameter; the rank analysis is kept as a diagnostic.

    ``start``: a MAP fit to start the iterations from (its frame is this model's reference already).
    """
    x0 = model.nominal_vector()
    if spec.earlier is not None:
        x0 = x0.clone()
        keep = model.layout.base_slice
        earlier = spec.earlier.x.to(x0)
        x0 = torch.cat([earlier[: keep.start], x0[keep], earlier[keep.stop :]])
    names = model.layout.names
    prior = spec.build(list(names), problem.free, x0)
    flat = int((~torch.isfinite(prior.sigma)).sum())
    if problem.rows_per_pose * len(data) <= flat:
        raise DataError(f"{len(data)} poses give {problem.rows_per_pose * len(data)} equations, no more than the "
                        f"{flat} parameters without a prior (instrument frame); measure more poses", path=data.source)
    _, jac0 = problem.jacobian(x0)
    report = analyze(jac0, problem.names)
    notes = []
    if report.dependent:
        msg = (
            f"rank analysis (diagnostic): {len(report.dependent)} parameter(s) the data cannot separate from others "
            "stay at their prior, with its sigma: "
            + "; ".join(
                f"{n} (confounded with {', '.join(p for p, _ in partners[:2]) or 'nothing'})"
                for n, partners in report.dependent.items()
            )
        )
        notes.append(msg)
        warnings.warn(msg, IdentifiabilityWarning, stacklevel=3)
    notes.append(f"prior: {spec.describe()}")
    x_start, sigma_start = x0, None
    if start is not None:
        # the start's frame is folded into this model's reference (its base entries are zero); entries
        # this spec fixes (the MDH table of the nominal robot) stay at the prior mean
        x_start = x0.clone()
        x_start[problem.free] = start.x.to(x0)[problem.free]
        sigma_start = start.noise_sigma_m
    fit = solve_map(problem, prior, x_start, identifier, units=units, rows_per_pose=problem.rows_per_pose,
                    start_sigma=sigma_start)
    reference, x = model.recentered(fit.x)
    model.T_reference = reference
    return CalibrationResult(
        model=model, x=x, free=problem.free.clone(), covariance=fit.covariance, sigma_residual_m=fit.noise_sigma,
        identifiability=report, solve=fit.solve, method=identifier.name, notes=notes, prior=prior,
        noise_sigma_m=fit.noise_sigma, log_evidence=fit.log_evidence,
    )
