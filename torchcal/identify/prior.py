"""Prior knowledge of a robot's parameters and the maximum-a-posteriori (MAP) fit that uses it.

A robot is built to a drawing within manufacturing tolerances, and an earlier calibration is
known with its covariance. The fit combines that prior with the measurements: it minimizes

    |r(x)|^2 / s^2 + (x - x0)^T Lambda (x - x0)

(``r`` the data residuals, ``s`` their standard deviation per coordinate, ``x0`` the prior mean,
``Lambda`` the prior precision) by damped Gauss-Newton (the project's Levenberg-Marquardt) on the
stacked residual ``[r / s ; W (x - x0)]`` with ``W^T W = Lambda`` (times ``s``, see :class:`PriorProblem`). Directions the data cannot see
stay at the prior with the prior's uncertainty, instead of being cut (the earlier rank cut) or
fitted to noise. ``s`` is the data's own: ``s^2 = |r|^2 / (m - p_eff)`` with ``p_eff`` the
effective number of parameters the data determine, iterated with the solution.

Default prior (1-sigma per parameter kind, :class:`Tolerances`): MDH lengths ``a, d`` 0.5 mm,
MDH angles ``alpha, beta`` 0.05 deg, joint zero offsets ``theta`` 0.1 deg, tool point 10 mm per
axis, tool rotation 5 deg; the instrument frame has no prior (it is found by registration).
A parameter further than 3 sigma of the (unscaled) tolerance from its prior mean is *beyond
tolerance* and named in a warning. The robot file may state its own values in a top-level
``calibration_prior`` mapping with the same keys (``length_mm``, ``angle_deg``,
``joint_offset_deg``, ``tool_mm``, ``tool_deg``); fit options ``tolerance_*`` override both.
A ``scale`` multiplies every sigma of the MDH table (chosen by grouped cross-validation, see
:mod:`torchcal.model_selection.prior_scale`); scale 0 is the nominal robot: the MDH table fixed
at its prior, frame and tool fitted.

The posterior covariance is ``(J^T J / s^2 + Lambda)^-1``, widened per parameter to the
cluster-robust estimate ``H^-1 (B + Lambda) H^-1`` (``B`` the per-region outer products of the
data gradient) where that is larger, as :mod:`torchcal.identify.uncertainty` does without a prior.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch
import yaml

from torchcal.core.errors import ModelError
from torchcal.identify.base import Identifier, SolveResult
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.problem import LeastSquaresProblem
from torchcal.identify.uncertainty import _widened
from torchcal.kinematics.robot import read_robot_text
from torchcal.kinematics.robot_checks import StrictSafeLoader

#: Parameter kinds of the error layout and how a name maps to one.
KINDS = ("length_mm", "angle_deg", "joint_offset_deg", "tool_mm", "tool_deg")
#: A parameter beyond this many (unscaled) prior sigmas from its prior mean is named in a warning.
TOLERANCE_SIGMAS = 3.0
#: The first solve weights the data with this fraction of the starting residual's RMS as sigma.
START_FACTOR = 0.3
#: A MAP solve stops when a step would lower chi^2 (the cost in units of the noise variance) by less
#: than this: the estimate is then within about sqrt(2 x 0.001) = 0.045 posterior sigma of the
#: minimum, where Levenberg-Marquardt's relative tolerance alone crawls on along the directions the
#: prior barely holds (correlated parameters) for as many steps again.
CHI2_TOLERANCE = 1e-3
#: Levenberg-Marquardt's starting damping (relative to the largest diagonal) in a MAP solve.
MAP_INITIAL_DAMPING = 1e-12


def parameter_kind(name: str) -> str | None:
    """The tolerance kind of a layout parameter name (``None``: the instrument frame, no prior)."""
    if name.startswith("base_"):
        return None
    if name.startswith("tool_"):
        return "tool_deg" if name[5:].startswith("r") else "tool_mm"
    field_name = name.rstrip("0123456789")
    if field_name in ("a", "d"):
        return "length_mm"
    if field_name in ("alpha", "beta"):
        return "angle_deg"
    if field_name == "theta":
        return "joint_offset_deg"
    return None


@dataclass(frozen=True)
class Tolerances:
    """1-sigma of the prior per parameter kind (mm, deg). See the module docstring for the defaults."""

    length_mm: float = 0.5
    angle_deg: float = 0.05
    joint_offset_deg: float = 0.1
    tool_mm: float = 10.0
    #: The tool's (probe's) rotation on the flange, fitted only where orientations were measured: no prior by
    #: default (``inf``), as the instrument frame's. A 6-D probe is mounted at any angle (the UR10's T-Mac at
    #: -90 deg about z), and the orientations determine it to hundredths of a degree.
    tool_deg: float = math.inf

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            free = f.name == "tool_deg" and value == math.inf
            if not (isinstance(value, (int, float)) and (math.isfinite(value) or free) and value > 0):
                raise ModelError(f"tolerance {f.name} must be a positive number, got {value!r}")

    def sigma_si(self, name: str) -> float:
        """The prior 1-sigma of parameter ``name`` in SI (m or rad); ``inf`` for the instrument frame."""
        kind = parameter_kind(name)
        if kind is None:
            return math.inf
        value = float(getattr(self, kind))
        return value * 1e-3 if kind.endswith("_mm") else math.radians(value)

    def describe(self) -> str:
        rotation = "rotation free" if self.tool_deg == math.inf else f"{self.tool_deg:g} deg"
        return (f"lengths {self.length_mm:g} mm, angles {self.angle_deg:g} deg, joint offsets {self.joint_offset_deg:g} deg, "
                f"tool {self.tool_mm:g} mm / {rotation} (1 sigma); instrument frame free")


def robot_file_tolerances(source: str | None) -> dict[str, float]:
    """The ``calibration_prior`` mapping of a YAML robot file (empty when it has none)."""
    if not source or Path(source).suffix.lower() not in (".yaml", ".yml") or not Path(source).is_file():
        return {}
    doc = yaml.load(read_robot_text(Path(source)), Loader=StrictSafeLoader)  # as the robot loader reads it: 1e-2 a number
    section = doc.get("calibration_prior") if isinstance(doc, dict) else None
    if section is None:
        return {}
    if not isinstance(section, dict):
        raise ModelError(f"{source}: calibration_prior must be a mapping with keys {', '.join(KINDS)}")
    unknown = sorted(set(section) - set(KINDS))
    if unknown:
        raise ModelError(f"{source}: calibration_prior has unknown key(s) {unknown}; known: {', '.join(KINDS)}")
    out = {}
    for key, value in section.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ModelError(f"{source}: calibration_prior.{key} must be a positive number, got {value!r}")
        out[key] = float(value)
    return out


def resolve_tolerances(robot_source: str | None, options: dict[str, float | None] | None = None) -> Tolerances:
    """Built-in defaults, then the robot file's ``calibration_prior``, then the options (non-``None`` values)."""
    values: dict[str, float] = dict(robot_file_tolerances(robot_source))
    for key, value in (options or {}).items():
        if value is not None:
            values[key] = float(value)
    return Tolerances(**values)


@dataclass(frozen=True)
class EarlierModel:
    """An earlier calibration as prior: its parameter vector and the covariance of some of its entries (SI).

    ``indices`` name the entries of the layout that ``covariance`` covers; the instrument frame is
    never taken from it (the instrument stands elsewhere), other entries fall back to the tolerances.
    """

    x: torch.Tensor
    indices: torch.Tensor
    covariance: torch.Tensor
    label: str


@dataclass(frozen=True)
class PriorSpec:
    """What the prior is: tolerances (or an earlier model) and a scale on every sigma.

    ``scale`` multiplies the sigmas of the MDH table (the tool keeps its tolerance); 0 is the
    nominal robot (MDH table at its prior mean, frame and tool fitted).
    """

    tolerances: Tolerances = field(default_factory=Tolerances)
    scale: float = 1.0
    earlier: EarlierModel | None = None

    @property
    def nominal(self) -> bool:
        return self.scale == 0.0

    def label(self) -> str:
        if self.nominal:
            return "nominal"
        return f"prior x{self.scale:g}"

    def describe(self) -> str:
        if self.earlier is not None:
            source = f"earlier model {self.earlier.label} (its covariance; tolerances where it has none)"
        else:
            source = f"manufacturing tolerances: {self.tolerances.describe()}"
        if self.nominal:
            return f"nominal robot: MDH table fixed at the prior mean ({source}); frame and tool fitted"
        return f"{source}, sigmas scaled x{self.scale:g}"

    def build(self, names: list[str], free: torch.Tensor, nominal: torch.Tensor) -> Prior:
        """The prior over the entries ``free`` of a layout named ``names``; ``nominal`` the layout's nominal vector."""
        idx = free.tolist()
        mean = nominal.clone()
        tol = torch.tensor([self.tolerances.sigma_si(names[i]) for i in idx], dtype=torch.float64)
        # the scale is on the robot's manufacturing (the MDH table); the tool is the user's, never scaled
        table = torch.tensor([not names[i].startswith("tool_") for i in idx])
        sigma = torch.where(table & torch.isfinite(tol), tol * self.scale, tol)  # no prior stays inf (not inf * 0)
        precision = torch.diag(torch.where(torch.isfinite(sigma), 1.0 / sigma.clamp_min(1e-300) ** 2, 0.0))
        if self.earlier is not None:
            e = self.earlier
            take = [k for k, i in enumerate(e.indices.tolist()) if i in idx and parameter_kind(names[i]) is not None]
            rows = [idx.index(int(e.indices[k])) for k in take]
            for k in take:
                mean[int(e.indices[k])] = e.x[int(e.indices[k])]
            if take:
                # scaled as the tolerances are: the table's entries, never the tool's (the user's)
                factor = torch.tensor([1.0 if names[int(e.indices[k])].startswith("tool_") else self.scale for k in take],
                                      dtype=torch.float64)
                block = factor[:, None] * e.covariance[take][:, take] * factor[None, :]
                block_precision = torch.linalg.pinv(block, hermitian=True)
                r = torch.tensor(rows)
                precision[r[:, None], r[None, :]] = block_precision
                cov = torch.linalg.pinv(precision, hermitian=True)
                sigma = torch.where(torch.isfinite(sigma), cov.diagonal().clamp_min(0).sqrt(), sigma)
        values, vectors = torch.linalg.eigh(0.5 * (precision + precision.T))
        root = values.clamp_min(0).sqrt()[:, None] * vectors.T
        return Prior(names=[names[i] for i in idx], free=free, mean=mean, sqrt_precision=root, precision=precision,
                     sigma=sigma, tolerance_sigma=tol, spec=self)


@dataclass
class Prior:
    """A Gaussian prior over the free entries of a parameter vector (SI).

    Attributes:
        names: free parameter names; free: their indices.
        mean: ``(P,)`` prior mean of the whole vector (entries not free are fixed there).
        sqrt_precision: ``(K, K)`` ``W`` with ``W^T W = precision``.
        precision: ``(K, K)`` prior precision (0 rows: no prior, the instrument frame).
        sigma: ``(K,)`` prior 1-sigma (``inf`` without a prior).
        tolerance_sigma: ``(K,)`` the unscaled tolerance sigma (the warning's limit is 3 of these).
        spec: what the prior was built from.
    """

    names: list[str]
    free: torch.Tensor
    mean: torch.Tensor
    sqrt_precision: torch.Tensor
    precision: torch.Tensor
    sigma: torch.Tensor
    tolerance_sigma: torch.Tensor
    spec: PriorSpec

    def extended(self, free: torch.Tensor, extra: int, size: int, extra_sigma: torch.Tensor | None = None) -> Prior:
        """This prior followed by ``extra`` free entries (joint-space coefficients, mean 0).

        ``extra_sigma`` ``(extra,)``: their independent prior 1-sigma (SI; ``inf``: no prior, the
        default for every one).

        ``free``: the indices of the extended problem (this prior's, then the ``extra`` ones);
        ``size``: the length of the extended parameter vector. The mean is padded to ``size``, not
        to the largest free index: with every extra coefficient dropped (``extra`` 0) that index
        lies inside this prior's vector.
        """
        k = len(self.names)
        precision = torch.zeros(k + extra, k + extra, dtype=torch.float64)
        precision[:k, :k] = self.precision
        root = torch.zeros_like(precision)
        root[:k, :k] = self.sqrt_precision
        sigma = torch.full((extra,), math.inf, dtype=torch.float64) if extra_sigma is None else extra_sigma.to(torch.float64)
        if len(sigma) != extra:
            raise ModelError(f"extra_sigma needs {extra} entries, got {len(sigma)}")
        root[k:, k:] = torch.diag(1.0 / sigma)  # 1 / inf = 0: no prior
        precision[k:, k:] = torch.diag(sigma**-2)
        if size < len(self.mean) or (len(free) and int(free.max()) >= size):
            raise ModelError(f"an extended prior of length {size} must hold the {len(self.mean)} entries of the prior "
                             "and every free index")
        mean = torch.cat([self.mean, torch.zeros(size - len(self.mean), dtype=self.mean.dtype)])
        return replace(self, names=[*self.names, *[f"extra{i}" for i in range(extra)]], free=free, mean=mean,
                       precision=precision, sqrt_precision=root, sigma=torch.cat([self.sigma, sigma]),
                       tolerance_sigma=torch.cat([self.tolerance_sigma, sigma]))


class PriorProblem:
    """The stacked MAP residual ``[r(x) ; s W (x_free - mean_free)]`` of an inner least-squares problem.

    That is ``s`` times ``[r / s ; W (x - x0)]``: the same minimizer, with the data rows in their own
    units, so the identifier's damping (``lambda`` relative to the largest diagonal of ``J^T J``)
    acts as it does without a prior.
    """

    def __init__(self, inner: LeastSquaresProblem, prior: Prior, noise_sigma: float) -> None:
        self.inner, self.prior, self.noise_sigma = inner, prior, float(noise_sigma)
        self._mean_free = prior.mean[inner.free]

    @property
    def free(self) -> torch.Tensor:
        return self.inner.free

    @property
    def names(self) -> list[str]:
        return self.inner.names

    def _prior_rows(self, x: torch.Tensor) -> torch.Tensor:
        return self.prior.sqrt_precision.to(x) @ (x[self.free] - self._mean_free.to(x))

    def residuals(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.inner.residuals(x), self.noise_sigma * self._prior_rows(x)])

    def jacobian(self, x: torch.Tensor, columns: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        r, jac = self.inner.jacobian(x, columns)
        w = self.prior.sqrt_precision.to(x)
        if columns is not None:
            position = {int(i): k for k, i in enumerate(self.free.tolist())}
            w = w[:, [position[int(c)] for c in columns.tolist()]]
        s = self.noise_sigma
        return torch.cat([r, s * self._prior_rows(x)]), torch.cat([jac, s * w])


@dataclass
class MapFit:
    """A MAP solution: ``x`` (full vector), posterior ``covariance`` over the free entries, the data's ``noise_sigma``
    (per coordinate, the inner problem's units) and the effective number of parameters the data determine."""

    x: torch.Tensor
    covariance: torch.Tensor
    noise_sigma: float
    effective_parameters: float
    solve: SolveResult
    log_evidence: float = math.nan


def _effective(jac: torch.Tensor, precision: torch.Tensor, s: float) -> tuple[torch.Tensor, float]:
    """Posterior precision ``H`` and ``p_eff = tr(H^-1 J^T J / s^2)`` (column-scaled for conditioning)."""
    data = jac.T @ jac / s**2
    h = data + precision.to(jac)
    scale = h.diagonal().clamp_min(1e-300).sqrt()
    inv = torch.linalg.pinv(h / torch.outer(scale, scale), hermitian=True) / torch.outer(scale, scale)
    return h, float((inv * data).sum())


def solve_map(problem: LeastSquaresProblem, prior: Prior, x0: torch.Tensor, identifier: Identifier, *,
              units: np.ndarray | None = None, rows_per_pose: int = 3, iterations: int = 6,
              start_sigma: float | None = None) -> MapFit:
    """MAP estimate of ``problem.free`` under ``prior``, the noise sigma re-estimated with the solution.

    ``x0``: the starting point (the prior mean, or a warm start such as the fit on all poses);
    ``start_sigma``: the noise sigma to start from (default: :data:`START_FACTOR` of the starting
    residual's RMS). ``units``: ``(n,)`` configuration region of each pose (``rows_per_pose`` data
    rows each): the covariance is widened to the cluster-robust estimate where larger (module docstring).
    """
    r0 = problem.residuals(x0)
    m = r0.numel()
    # from the prior mean, start from a fraction of the starting residual: the prior then holds the
    # first solve well conditioned, and the re-estimated sigma settles within a few warm-started solves
    s = max(float(r0.norm()) / m**0.5 * START_FACTOR if start_sigma is None else float(start_sigma), 1e-300)
    x = x0.clone()
    solve = None
    if isinstance(identifier, LevenbergMarquardt):
        # the cost at the minimum is about m s^2 / 2: its relative tolerance as a chi^2 tolerance
        identifier = copy.copy(identifier)
        identifier.ftol = max(identifier.ftol, 2.0 * CHI2_TOLERANCE / m)
        # the prior makes every Gauss-Newton system well posed: start nearly undamped, so that steps
        # along the weakly held directions are not shrunk for many iterations (a bad step is still rejected)
        identifier.initial_damping = min(identifier.initial_damping, MAP_INITIAL_DAMPING)
    for _ in range(iterations):
        solve = identifier.solve(PriorProblem(problem, prior, s), x)  # type: ignore[arg-type]  # any LeastSquaresProblem
        x = solve.x
        r, jac = problem.jacobian(x)
        _, p_eff = _effective(jac, prior.precision, s)
        s_new = max((float(r @ r) / max(m - p_eff, 1.0)) ** 0.5, 1e-300)
        done = abs(s_new / s - 1.0) < 0.02
        s = s_new
        if done:
            break
    assert solve is not None
    cov, p_eff = posterior_covariance(jac, r, prior.precision, s, units, rows_per_pose)
    evidence = log_evidence(jac, r, prior.precision, x[problem.free] - prior.mean[problem.free].to(x), s)
    return MapFit(x=x, covariance=cov, noise_sigma=s, effective_parameters=p_eff, solve=solve, log_evidence=evidence)


def log_evidence(jac: torch.Tensor, residuals: torch.Tensor, precision: torch.Tensor, offset: torch.Tensor,
                 s: float) -> float:
    """Log marginal likelihood of the data under the prior, the model linearised at the MAP ``x``.

    ``jac`` ``(m, K)`` and ``residuals`` ``(m,)`` of the data at ``x``; ``offset`` ``x - mean``
    over the free entries; ``s`` the noise sigma. The Laplace form (closed for a linear model)::

        -|r|^2 / (2 s^2) - d^T Lambda d / 2 - log det H / 2 + log det Lambda_p / 2
        - m log(2 pi s^2) / 2 + (K - K_p) log(2 pi) / 2

    with ``H = J^T J / s^2 + Lambda`` and ``Lambda_p`` the precision over the ``K_p`` entries that
    have a prior; entries without one (the instrument frame) take a flat prior whose width is the
    same for every candidate, so it cancels when candidates are compared. A candidate that fixes
    parameters (the nominal robot) is the limit of a vanishing prior sigma there: those entries
    drop out of ``H`` and ``Lambda_p`` alike.
    """
    m, k = jac.shape
    lam = precision.to(jac)
    h = jac.T @ jac / s**2 + lam
    scale = h.diagonal().clamp_min(1e-300).sqrt()
    _, logdet_h = torch.linalg.slogdet(h / torch.outer(scale, scale))
    logdet_h = float(logdet_h) + 2.0 * float(scale.log().sum())
    with_prior = lam.abs().sum(0) > 0
    k_p = int(with_prior.sum())
    logdet_p = float(torch.linalg.slogdet(lam[with_prior][:, with_prior])[1]) if k_p else 0.0
    fit = float(residuals @ residuals) / s**2 + float(offset @ lam @ offset)
    return (-0.5 * fit - 0.5 * logdet_h + 0.5 * logdet_p - 0.5 * m * math.log(2 * math.pi * s**2)
            + 0.5 * (k - k_p) * math.log(2 * math.pi))


def posterior_covariance(jac: torch.Tensor, residuals: torch.Tensor, precision: torch.Tensor, s: float,
                         units: np.ndarray | None = None, rows_per_pose: int = 3) -> tuple[torch.Tensor, float]:
    """Posterior covariance ``(K, K)`` and ``p_eff``; widened to the cluster-robust estimate per parameter."""
    h, p_eff = _effective(jac, precision, s)
    scale = h.diagonal().clamp_min(1e-300).sqrt()
    inv = torch.linalg.pinv(h / torch.outer(scale, scale), hermitian=True) / torch.outer(scale, scale)
    m = jac.shape[0]
    if units is not None and len(units) and m == rows_per_pose * len(units) and len(np.unique(units)) >= 2:
        _, index = np.unique(np.repeat(np.asarray(units), rows_per_pose), return_inverse=True)
        groups = int(index.max()) + 1
        sums = torch.zeros(groups, jac.shape[1], dtype=jac.dtype, device=jac.device)
        sums.index_add_(0, torch.as_tensor(index, device=jac.device), jac * residuals[:, None] / s**2)
        factor = groups / (groups - 1) * (m - 1) / max(m - p_eff, 1.0)
        robust = inv @ (factor * (sums.T @ sums) + precision.to(jac)) @ inv
        inv = _widened(inv, robust)
    return inv, p_eff


# ----------------------------------------------------------------------------------- reporting


def prior_table(names: list[str], is_angle: list[bool], prior: Prior, x: torch.Tensor,
                covariance: torch.Tensor) -> list[dict]:
    """Per free parameter with a prior: prior and posterior value and sigma (mm / deg), moved by (prior sigmas),
    posterior / prior sigma. ``x`` the full vector, ``covariance`` over ``prior.free`` (the geometric block)."""
    rows = []
    post_sigma = covariance.diagonal().clamp_min(0).sqrt()
    for k, i in enumerate(prior.free.tolist()):
        sigma = float(prior.sigma[k])
        if not math.isfinite(sigma) or k >= len(post_sigma):
            continue
        unit, factor = ("deg", 180.0 / math.pi) if is_angle[i] else ("mm", 1e3)
        moved = float(x[i] - prior.mean[i])
        rows.append({
            "name": names[i], "unit": unit,
            "prior": float(prior.mean[i]) * factor, "prior_sigma": sigma * factor,
            "posterior": float(x[i]) * factor, "posterior_sigma": float(post_sigma[k]) * factor,
            "moved_sigmas": moved / sigma if sigma > 0 else 0.0,
            "sigma_ratio": float(post_sigma[k]) / sigma if sigma > 0 else 0.0,
            "beyond_tolerance": abs(moved) > TOLERANCE_SIGMAS * float(prior.tolerance_sigma[k]),
            "tolerance": TOLERANCE_SIGMAS * float(prior.tolerance_sigma[k]) * factor,
        })
    return rows


def beyond_tolerance_warning(rows: list[dict]) -> str | None:
    """One line naming every parameter further than its tolerance (3 unscaled sigmas) from the prior mean."""
    found = [f"{r['name']} {r['posterior'] - r['prior']:+.4g} {r['unit']} (tolerance {r['tolerance']:.3g})"
             for r in rows if r["beyond_tolerance"]]
    if not found:
        return None
    return (f"{len(found)} parameter(s) moved beyond their manufacturing tolerance: {', '.join(found)}; "
            "check the robot file and the measurement set-up, or widen the prior if this robot is built so")


def taught_summary(rows: list[dict]) -> str:
    """One line: how many parameters the data moved and sharpened, how many they left at the prior."""
    if not rows:
        return "prior: no parameter with a prior was estimated"
    at_prior = [r["name"] for r in rows if r["sigma_ratio"] > 0.9]
    sharpened = len(rows) - len(at_prior)
    text = f"prior vs posterior: the data sharpened {sharpened} of {len(rows)} parameters (posterior sigma < 0.9 prior)"
    if at_prior:
        text += f"; {len(at_prior)} stay at their prior (the data do not see them): {', '.join(at_prior)}"
    return text
