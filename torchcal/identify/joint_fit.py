"""Geometry identified jointly with joint-space errors (gravity compliance, periodic joint errors).

Every joint-space term is linear in its coefficients: ``dq_j = sum_k c_kj B_kj(q)`` with a basis
``B (n, K, N)`` evaluated at the commanded joints (unit-weight gravity torques,
:mod:`torchcal.identify.compliance`; ``sin q_j`` / ``cos q_j``, :mod:`torchcal.identify.harmonics`).
The TCP displacement per coefficient is ``B_kj`` times the ``theta_j`` column of the position
Jacobian, so the identification Jacobian is the geometric one extended by those columns.

Coefficients the data cannot separate from the geometry (or from each other) are found by the
same identifiability analysis as geometric parameters, stay at zero and are named in an
:class:`~torchcal.core.errors.IdentifiabilityWarning`. Which terms to use is chosen by the grouped
cross-validation of :mod:`torchcal.model_selection.structure`, never on a test set.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace

import numpy as np
import torch

from torchcal.core.errors import IdentifiabilityWarning
from torchcal.data.measurements import Measurements
from torchcal.identify.compliance import (
    _ZERO_COLUMN,
    POINT_SETS,
    GravityCompliance,
    gravity_torque_basis,
)
from torchcal.identify.harmonics import (
    HARMONIC_SETS,
    SMOOTHNESS_POWER,
    SMOOTHNESS_SCALES_RAD,
    JointHarmonics,
    harmonic_basis,
    is_series,
    term_order,
)
from torchcal.identify.identifiability import analyze
from torchcal.identify.joint_columns import pose_and_columns, position_and_columns
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.prior import log_evidence, solve_map
from torchcal.identify.series_frames import per_series_registered
from torchcal.identify.uncertainty import covariance
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import RobotModel

CV_TOLERANCE = 0.01  # keep the simplest option whose CV RMS is within 1 % of the best


class JointErrorProblem:
    """A calibration problem over ``[x (P), c (K)]``: geometry plus joint-space coefficients.

    ``basis (n, R, N)`` holds the joint-error basis rows; ``columns`` the ``(row, joint)`` of each
    coefficient and ``column_names`` its name. Offers what an
    :class:`~torchcal.identify.base.Identifier` uses (``free``, ``names``, ``residuals``,
    ``jacobian``, ``with_free``). Residuals in the instrument frame, m; where the model was fitted to
    measured orientations (``model.with_orientation``) each pose adds its rotation rows, rad times
    ``orientation_weight_m_per_rad``, as :class:`~torchcal.identify.problem.CalibrationProblem`'s:
    the joint-space terms turn the tool as they move the point, and the orientations judge both.
    """

    def __init__(self, model: ErrorModel, data: Measurements, basis: torch.Tensor, free: torch.Tensor,
                 columns: list[tuple[int, int]], column_names: list[str] | None = None,
                 orientation_weight_m_per_rad: float = 1.0) -> None:
        self.model, self.data, self.basis, self.free = model, data, basis, free
        self.columns = columns
        # flat (row, joint) index of each coefficient in the (R, N) coefficient table
        self._flat = torch.tensor([k * basis.shape[2] + j for k, j in columns], dtype=torch.long)
        self.column_names = column_names or [f"joint_error{k}_{j + 1}" for k, j in columns]
        self.size = model.layout.size
        self.use_orientation = bool(model.with_orientation and data.rotation is not None)
        self.orientation_weight_m_per_rad = orientation_weight_m_per_rad
        self.rows_per_pose = 6 if self.use_orientation else 3

    @property
    def names(self) -> list[str]:
        geo = self.model.layout.names
        return [geo[i] if i < self.size else self.column_names[i - self.size] for i in self.free.tolist()]

    def _split(self, xe: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = xe[: self.size]
        c = torch.zeros(self.basis.shape[1] * self.basis.shape[2], dtype=xe.dtype)
        c[self._flat] = xe[self.size :]
        c = c.reshape(self.basis.shape[1], self.basis.shape[2])
        return x, self.data.q + (self.basis * c).sum(1)

    def _pose_rows(self, pose: torch.Tensor) -> torch.Tensor:
        """``(n, 6)`` position and weighted rotation residuals of TCP poses ``(n, 4, 4)``."""
        assert self.data.rotation is not None
        dp = self.data.position.to(pose) - pose[..., :3, 3]
        dr = tf.so3_log(self.data.rotation.to(pose) @ pose[..., :3, :3].transpose(-1, -2))
        return torch.cat([dp, dr * self.orientation_weight_m_per_rad], -1)

    def residuals(self, xe: torch.Tensor) -> torch.Tensor:
        x, q = self._split(xe)
        if self.use_orientation:
            return self._pose_rows(self.model.tcp_pose(q, x)).reshape(-1)
        return per_series_registered(self.data, (self.data.position - self.model.tcp_position(q, x)).reshape(-1))[0]

    def jacobian(self, xe: torch.Tensor, columns: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        columns = self.free if columns is None else columns
        x, q = self._split(xe)

        def joint_column(i: int, jac_theta: torch.Tensor) -> torch.Tensor:
            k, j = self.columns[i]
            return jac_theta[..., j] * self.basis[:, k, j : j + 1]

        if self.use_orientation:  # as CalibrationProblem's 6-D rows (no pooled series: a 6-D fit has one frame)
            pose, full = pose_and_columns(self.model, q, x, columns, self.size, joint_column)
            full = full.clone()
            full[:, 3:] *= self.orientation_weight_m_per_rad
            return self._pose_rows(pose).reshape(-1), -full.reshape(-1, full.shape[-1])
        pred, full = position_and_columns(self.model, q, x, columns, self.size, joint_column)
        r, jac = per_series_registered(self.data, (self.data.position - pred).reshape(-1), -full.reshape(-1, full.shape[-1]))
        assert jac is not None
        return r, jac

    def with_free(self, free: torch.Tensor) -> JointErrorProblem:
        return JointErrorProblem(self.model, self.data, self.basis, free, self.columns, self.column_names,
                                 self.orientation_weight_m_per_rad)


def _candidate_columns(basis: torch.Tensor, points: tuple[str, ...], terms: tuple[str, ...]) -> tuple[list, list]:
    """``(row, joint)`` and names of every coefficient whose basis column is not identically zero."""
    scale = basis.abs().amax(0)  # (R, N)
    labels = [f"c_{p}" for p in points] + [f"harm_{t}" for t in terms]
    cols = [(k, j) for k in range(basis.shape[1]) for j in range(basis.shape[2]) if float(scale[k, j]) > _ZERO_COLUMN]
    return cols, [f"{labels[k]}{j + 1}" for k, j in cols]


def narrow_joints(q: torch.Tensor, min_range_deg: float) -> list[int]:
    """Joints (0-based) whose commanded range in ``q (n, N)`` rad spans less than ``min_range_deg``."""
    span = torch.rad2deg(q.amax(0) - q.amin(0))
    return [j for j in range(q.shape[1]) if float(span[j]) < min_range_deg]


def fit_joint_errors(robot: RobotModel, data: Measurements, geometric, points: tuple[str, ...] = (),
                     harmonics: tuple[str, ...] = (), harmonic_min_range_deg: float = 0.0,
                     units: np.ndarray | None = None):
    """Refine a geometric :class:`~torchcal.identify.calibrate.CalibrationResult` jointly with joint-space errors.

    ``points``: gravity points (``tcp``, ``elbow``); ``harmonics``: harmonic terms (``sin``,
    ``cos``), only on joints whose commanded range in ``data`` spans ``harmonic_min_range_deg``:
    over a short arc ``a sin q + b cos q`` is an offset plus a slope, fitted as such and wild
    outside the arc (fitted on UR10 series C, where joint 2 spans 96 deg, first harmonics score
    1.40 mm on series B against 0.90 for geometry alone). Returns a result of the same type with ``compliance`` / ``harmonics`` set;
    ``covariance`` is the geometric block of the joint covariance (the marginal of the geometry),
    ``joint_covariance`` the whole of it with ``joint_coefficients`` naming the terms' coefficients;
    ``units`` (configuration region of each pose) widens it as in
    :func:`~torchcal.identify.uncertainty.covariance`.
    """
    if not points and not harmonics:
        return geometric
    data = data.to("cpu")
    harmonic = harmonic_basis(data.q, harmonics)
    narrow = narrow_joints(data.q, harmonic_min_range_deg) if harmonics else []
    harmonic[:, :, narrow] = 0.0
    basis = torch.cat([gravity_torque_basis(robot, data.q, points), harmonic], 1)
    cols, names = _candidate_columns(basis, points, harmonics)
    size = geometric.model.layout.size
    n_geo = len(geometric.free)
    problem = JointErrorProblem(geometric.model, data, basis, torch.cat([geometric.free, torch.arange(size, size + len(cols))]),
                                cols, names)
    x0 = torch.cat([geometric.x, torch.zeros(len(cols), dtype=torch.float64)])
    # what the data cannot tell apart from the geometry (kept first) or earlier terms stays at zero
    _, jac0 = problem.jacobian(x0)
    report = analyze(jac0, problem.names)
    dropped = [n for n in names if n in report.dependent]
    notes = list(geometric.notes)
    if narrow:
        notes.append(f"no first harmonics on joint(s) {', '.join(str(j + 1) for j in narrow)}: their range in the "
                     f"data spans less than {harmonic_min_range_deg:g} deg")
    if dropped:
        msg = (f"{len(dropped)} joint-space coefficient(s) cannot be separated from the geometry or the terms "
               "before them and stay at zero: "
               + "; ".join(f"{n} (confounded with {', '.join(p for p, _ in report.dependent[n][:2]) or 'nothing'})"
                           for n in dropped))
        notes.append(msg)
        warnings.warn(msg, IdentifiabilityWarning, stacklevel=2)
    kept = [i for i, n in enumerate(names) if n not in dropped]
    free = torch.cat([geometric.free, size + torch.tensor(kept, dtype=torch.long)])
    smooth = is_series(harmonics)
    prior_scale = None
    if geometric.prior is not None:
        # the geometry keeps its prior (identify.prior); gravity terms and first harmonics have none,
        # a Fourier series its smoothness prior (identify.harmonics), whose scale the evidence chooses
        scales = SMOOTHNESS_SCALES_RAD if smooth else (None,)
        sized = problem.with_free(free)

        def prior_of(scale):
            extra_sigma = None if scale is None else _series_sigma(cols, kept, len(points), harmonics, scale)
            return geometric.prior.extended(free, len(kept), size + len(cols), extra_sigma)

        # the geometry's noise sigma as the start: the joint terms lower it, a warm solve or two follow
        prior_scale = scales[len(scales) // 2]
        fit = solve_map(sized, prior_of(prior_scale), x0, LevenbergMarquardt(), units=units, rows_per_pose=sized.rows_per_pose,
                        start_sigma=geometric.noise_sigma_m)
        if smooth:
            # the evidence of every scale from one Gauss-Newton step at this solution (the series is
            # linear in its coefficients, the chain nearly so at these sizes); the best is solved in full
            evidence, starts = _evidence_scan(sized, fit, [prior_of(v) for v in scales])
            best = int(np.argmax(evidence))
            if scales[best] != prior_scale:
                prior_scale = scales[best]
                fit = solve_map(sized, prior_of(prior_scale), starts[best], LevenbergMarquardt(), units=units,
                                rows_per_pose=sized.rows_per_pose,
                                start_sigma=fit.noise_sigma)
        sol, cov, sigma = fit.solve, fit.covariance, fit.noise_sigma
        if smooth:
            notes.append(f"joint Fourier series: smoothness prior scale {prior_scale:.2g} rad (order k: scale / k^"
                         f"{SMOOTHNESS_POWER:g}) chosen by the evidence among {', '.join(f'{v:g}' for v in scales)}")
    else:
        sol = LevenbergMarquardt().solve(problem.with_free(free), x0)
        r, jac = problem.with_free(free).jacobian(sol.x)
        cov, sigma = covariance(jac, r, units)
    rows = basis.shape[1]
    values = torch.zeros(rows, robot.dof, dtype=torch.float64)
    sigmas = torch.zeros(rows, robot.dof, dtype=torch.float64)
    extra_sigma = cov.diagonal()[n_geo:].clamp_min(0).sqrt()
    for pos, i in enumerate(kept):
        k, j = cols[i]
        values[k, j] = sol.x[size + i]
        sigmas[k, j] = extra_sigma[pos]
    x = sol.x[:size].clone()
    reference, x = geometric.model.recentered(x)
    model = ErrorModel(robot, with_orientation=geometric.model.with_orientation,
                       parallel_threshold_deg=geometric.model.parallel_threshold_deg, T_instrument_base=reference)
    compliance = GravityCompliance(points, values[: len(points)]) if points else None
    fitted = JointHarmonics(values[len(points) :], sigmas[len(points) :], prior_scale) if harmonics else None
    terms = ([f"gravity compliance at {'+'.join(points)}"] if points else []) + ([fitted.label] if fitted else [])
    notes.append(f"{' and '.join(terms)} identified with the geometry ({len(kept)} coefficients)")
    return replace(geometric, model=model, x=x, covariance=cov[:n_geo, :n_geo], sigma_residual_m=sigma,
                   joint_covariance=cov.clone(), joint_coefficients=torch.tensor([cols[i] for i in kept], dtype=torch.long).reshape(-1, 2),
                   noise_sigma_m=sigma if geometric.prior is not None else geometric.noise_sigma_m,
                   notes=notes, compliance=compliance, harmonics=fitted)


def _evidence_scan(problem: JointErrorProblem, fit, priors: list) -> tuple[list[float], list[torch.Tensor]]:
    """Log evidence (:func:`~torchcal.identify.prior.log_evidence`) of each prior, the model linearised at ``fit.x``
    with its noise sigma; and each prior's MAP point after one Gauss-Newton step from there (a start)."""
    r, jac = problem.jacobian(fit.x)
    s = fit.noise_sigma
    free = problem.free
    out, starts = [], []
    for prior in priors:
        lam = prior.precision.to(jac)
        d = fit.x[free] - prior.mean[free].to(jac)
        h = jac.T @ jac / s**2 + lam
        step = -torch.linalg.solve(h, jac.T @ r / s**2 + lam @ d)
        x = fit.x.clone()
        x[free] = x[free] + step
        out.append(log_evidence(jac, r + jac @ step, lam, d + step, s))
        starts.append(x)
    return out, starts


def _series_sigma(cols: list[tuple[int, int]], kept: list[int], n_points: int, harmonics: tuple[str, ...],
                  scale: float) -> torch.Tensor:
    """Prior 1-sigma (rad) of each kept coefficient: ``scale / k^p`` for a term of order ``k``, none for gravity."""
    out = []
    for i in kept:
        row = cols[i][0]
        out.append(math.inf if row < n_points else scale / term_order(harmonics[row - n_points]) ** SMOOTHNESS_POWER)
    return torch.tensor(out, dtype=torch.float64)


def predicted_positions(result, q: torch.Tensor) -> torch.Tensor:
    """TCP positions (instrument frame, m) of a fit result, its joint-space errors included."""
    return result.model.tcp_position(JointSpaceErrors.of(result).effective_joints(result.model.robot, q), result.x)


def option_label(gravity: str, harmonics: str) -> str:
    """``none``, ``wrist``, ``elbow+wrist``, ``harmonics``, ``wrist+harmonics``, ``elbow+wrist+cubic+fourier2``, ..."""
    series = {"none": [], "first": ["harmonics"]}.get(harmonics, [harmonics])
    parts = ([gravity] if gravity != "none" else []) + series
    return "+".join(parts) or "none"


#: What ``auto`` compares: every classic gravity set with and without first harmonics, then the
#: learned joint-space models (a Fourier series of order 2 per joint with the elbow and wrist
#: compliance, and with the forearm's weight too), so that the CV chooses the order among 0, 1 and
#: 2. The forearm point (:mod:`torchcal.identify.compliance`) lowers the IRB 120 grouped CV from
#: 0.457 to 0.449 mm, where the CV chooses it, and the gate leaves every UR10 transfer as it was;
#: the series without it stays a candidate: where the two score alike over regions, the one with
#: the forearm can lose the blocks check that the other passes (UR10 B + C fitted together:
#: without that candidate, D 0.531 mm instead of 0.438; docs/joint_models.md). Order 4 is not among them: fitted
#: on the real sets it transferred worse than order 2 on every row (UR10 A -> C 2.80 against
#: 0.56 mm: over the partial wrist turns of A's grid it extrapolates; IRB 120 CV 0.462 against
#: 0.456), and it costs a fifth more CV. The cubic compliance (``elbow+wrist+cubic``) is not among
#: them either: fitted on UR10 series C it took -0.10 rad/m^3 on joint 4 and scored 0.96 mm on
#: series B against 0.55 mm without it, a tau^3 extrapolated past the torques of the fit, which the
#: grouped CV on C did not see (docs/joint_models.md).
AUTO_GRAVITY = ("none", "wrist", "elbow+wrist", "elbow+forearm+wrist")
AUTO_HARMONICS = ("none", "first")
LEARNED_OPTIONS = (("elbow+wrist", "fourier2"), ("elbow+forearm+wrist", "fourier2"))


def joint_error_options(gravity: str, harmonics: str) -> list[tuple[str, str]]:
    """``(gravity set, harmonic set)`` pairs to compare for the options ``gravity`` / ``harmonics`` (a set or ``auto``).

    Simplest (fewest coefficients) first: gravity sets add about ``N`` coefficients, first
    harmonics ``2 (N - 1)``, a series of order ``K`` ``2 K (N - 1)``. With both ``auto``: the
    classic pairs, then :data:`LEARNED_OPTIONS`.
    """
    for name, sets in ((gravity, POINT_SETS), (harmonics, HARMONIC_SETS)):
        if name not in sets and name != "auto":
            key = "gravity_compliance" if sets is POINT_SETS else "joint_harmonics"
            raise ValueError(f"unknown {key} '{name}'; choose auto or one of {sorted(sets)}")
    if gravity == "auto" and harmonics == "auto":
        return [(g, h) for h in AUTO_HARMONICS for g in AUTO_GRAVITY] + list(LEARNED_OPTIONS)
    if gravity == "auto":
        return [(g, harmonics) for g in AUTO_GRAVITY]
    if harmonics == "auto":
        return [(gravity, h) for h in AUTO_HARMONICS] + [(gravity, h) for h in dict.fromkeys(h for _, h in LEARNED_OPTIONS)]
    return [(gravity, harmonics)]


def fit_with_compliance(robot: RobotModel, data: Measurements, geometric, points: tuple[str, ...]):
    """Geometry refined jointly with gravity compliance only (see :func:`fit_joint_errors`)."""
    return fit_joint_errors(robot, data, geometric, points)
