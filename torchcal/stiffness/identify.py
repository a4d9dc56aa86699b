"""Joint stiffness identification from a stiffness file: log-parameterized Levenberg-Marquardt.

The VJM deflection is linear in the compliance entries: for a diagonal entry ``c`` of joint
``i``, component ``k`` (twist column ``b = J_i[:, k]``), its contribution to the TCP deflection
is ``c * b (b . W)``. Stacking those columns over poses gives a regressor ``G`` with
``dX = G c``. The stiffness ``k = 1 / c`` is fitted as ``s = log k``: positivity holds by
construction and the Jacobian ``dr/ds = -G c`` is scaled by each parameter's own size, which
is what the identifiability analysis needs.

Identifiability. The columns of the noise-weighted regressor are normalized (the SVD of the
scaled Jacobian, independent of the parameter magnitudes). A column that vanishes (e.g. joint
6 about its own axis when the TCP lies on that axis and only positions are measured) or a
direction of near-zero singular value (e.g. translations along two parallel joint axes) is not
observable: the parameter with the largest share of that null direction is removed, named in an
:class:`~torchcal.core.errors.IdentifiabilityWarning`, and treated as rigid; this repeats until the
rest is well conditioned. After the fit, parameters with a large relative standard deviation
are reported as poorly determined.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

from torchcal.core.errors import DataError, IdentifiabilityWarning, ModelError
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import RobotModel
from torchcal.stiffness.experiment import StiffnessData
from torchcal.stiffness.vjm import (
    SPRING_COMPONENTS,
    WrenchFrame,
    deflection,
    joint_poses,
    spring_names,
    twist_blocks,
    wrench_in_instrument,
)

DEFAULT_SIGMA_POSITION_M = 0.012e-3 * math.sqrt(2.0)
"""Noise of a loaded-minus-unloaded tracker difference (0.012 mm per point)."""
DEFAULT_SIGMA_ROTATION_RAD = math.radians(0.01) * math.sqrt(2.0)
"""Noise of a 6-DoF probe's rotation difference (0.01 deg per orientation)."""
_PRIORITY = {"tx": 0, "ty": 0, "tz": 0, "rx": 1, "ry": 1, "rz": 2}
STIFFNESS_BOUNDS = {"t": (1e3, 1e13), "r": (1e1, 1e11)}
"""Search range of translational (N/m) and rotational (N m/rad) stiffness; the upper end is rigid."""


def classic_names(n_joints: int) -> tuple[str, ...]:
    """One rotational stiffness per joint about its own axis: ``k_j{i}_rz``."""
    return tuple(f"k_j{i}_rz" for i in range(1, n_joints + 1))


def _parse_name(name: str, n_joints: int) -> tuple[int, int]:
    parts = name.split("_")
    if len(parts) != 3 or parts[0] != "k" or not parts[1].startswith("j") or parts[2] not in SPRING_COMPONENTS:
        raise ModelError(f"unknown stiffness parameter '{name}' (expected k_j<i>_<{'|'.join(SPRING_COMPONENTS)}>)")
    try:
        joint = int(parts[1][1:])
    except ValueError:
        raise ModelError(f"unknown stiffness parameter '{name}'") from None
    if not 1 <= joint <= n_joints:
        raise ModelError(f"stiffness parameter '{name}': the robot has joints 1..{n_joints}")
    return joint - 1, SPRING_COMPONENTS.index(parts[2])


def resolve_parameters(parameters: str | Sequence[str], n_joints: int) -> tuple[str, ...]:
    """``"classic"`` (one rotational spring per joint), ``"full"`` (6-D diagonal), or names."""
    if parameters == "classic":
        return classic_names(n_joints)
    if parameters == "full":
        return spring_names(n_joints)
    if isinstance(parameters, str):
        raise ModelError(f"parameters must be 'classic', 'full' or a list of names, got {parameters!r}")
    names = tuple(parameters)
    for name in names:
        _parse_name(name, n_joints)
    if len(set(names)) != len(names):
        raise ModelError("stiffness parameter names repeat")
    return names


def instrument_model(
    robot: RobotModel | ErrorModel,
    data: StiffnessData,
    x: torch.Tensor | None = None,
    *,
    device: str | torch.device = "cpu",
) -> tuple[ErrorModel, torch.Tensor]:
    """Error model whose ``instrument`` frame is the one of ``data``, and its parameter vector.

    With unloaded positions in ``data`` the ``instrument <- base`` transform is registered in
    closed form (Kabsch) from the model's TCP to them; without them it is the identity.
    ``x`` (default nominal) supplies calibrated geometry; its base correction is replaced.
    """
    options: dict = {}
    if isinstance(robot, ErrorModel):
        # keep the parameter layout of a calibrated model (tool rotation, Hayati rows)
        options = {"with_orientation": robot.with_orientation, "parallel_threshold_deg": robot.parallel_threshold_deg}
        robot = robot.robot
    if data.n_joints != robot.dof:
        raise DataError(f"has {data.n_joints} joint columns but the robot has {robot.dof} joints", path=data.path)
    base_model = ErrorModel(robot, device=device, **options)
    x = base_model.nominal_vector() if x is None else x.to(device=device, dtype=torch.float64).clone()
    x[base_model.layout.base_slice] = 0.0
    if data.unloaded is None:
        return base_model, x
    p_base = base_model.tcp_position(data.q.to(device), x)
    measured = data.unloaded.to(device)
    spread = torch.linalg.svdvals(measured - measured.mean(0))
    if len(data) < 3 or float(spread[1]) <= 1e-6 * max(float(spread[0]), 1e-12):
        raise DataError(
            "unloaded positions x,y,z are collinear or too few (need 3 non-collinear) to register the instrument frame",
            path=data.path,
            column="x",
        )
    T = tf.rigid_registration(p_base, measured)
    return ErrorModel(robot, T_instrument_base=T, device=device, **options), x


def stiffness_regressor(
    model: ErrorModel,
    q: torch.Tensor,
    x: torch.Tensor,
    wrench: torch.Tensor,
    names: Sequence[str],
    *,
    with_rotation: bool = False,
    wrench_frame: WrenchFrame = "tool",
) -> torch.Tensor:
    """``G`` ``(B, rows, K)`` with deflection ``dX = G c`` for the diagonal compliances ``c`` of ``names``.

    ``rows`` is 3 (position, m) or 6 (position, then rotation in rad), ``instrument`` frame.
    """
    pose = model.tcp_pose(q, x)
    blocks = twist_blocks(joint_poses(model, q, x), pose[..., :3, 3])
    w = wrench_in_instrument(wrench, pose, wrench_frame)
    idx = [_parse_name(n, model.robot.dof) for n in names]
    joints = torch.tensor([i for i, _ in idx], device=q.device)
    comps = torch.tensor([k for _, k in idx], device=q.device)
    cols = blocks.transpose(-1, -2)[..., joints, comps, :]  # (B, K, 6): twist columns
    gain = (cols * w.unsqueeze(-2)).sum(-1, keepdim=True)
    g = (cols * gain).transpose(-1, -2)  # (B, 6, K)
    return g if with_rotation else g[..., :3, :]


@dataclass(frozen=True)
class Identifiability:
    """Which candidate parameters the data can determine.

    Attributes:
        kept: names that stay in the fit.
        unobservable: names removed (no effect, or in a null direction), in removal order.
        confounded: for each removed name, the names sharing its null direction.
        singular_values: of the column-normalized weighted regressor of all candidates.
    """

    kept: tuple[str, ...]
    unobservable: tuple[str, ...]
    confounded: dict[str, tuple[str, ...]]
    singular_values: torch.Tensor


def analyse_identifiability(
    weighted: torch.Tensor, names: Sequence[str], *, rank_tol: float = 1e-7, zero_tol: float = 1e-9
) -> Identifiability:
    """SVD analysis of a weighted regressor ``(M, K)`` (rows already divided by their noise).

    Args:
        rank_tol: a normalized singular value below this is a null direction.
        zero_tol: a column whose norm is below this fraction of the largest has no effect.
    """
    names = list(names)
    norms = weighted.norm(dim=0)
    normalized = weighted / norms.clamp_min(1e-300)
    singular_all = torch.linalg.svdvals(normalized)
    keep = [bool(n > zero_tol * float(norms.max())) for n in norms]
    removed: list[str] = [n for n, k in zip(names, keep) if not k]
    confounded: dict[str, tuple[str, ...]] = dict.fromkeys(removed, ())
    while any(keep):
        cols = [i for i, k in enumerate(keep) if k]
        _, s, vh = torch.linalg.svd(normalized[:, cols], full_matrices=False)
        if float(s[-1]) >= rank_tol * float(s[0]):
            break
        null = vh[-1].abs()
        # Of the parameters sharing the null direction, drop the least plausible compliance:
        # translations before bending (rx, ry) before the joint's own axis (rz), which is the
        # dominant compliance of a geared joint; ties go to the largest share.
        shared = [j for j, v in enumerate(null.tolist()) if v > 0.1]
        worst = min(shared, key=lambda j: (_PRIORITY[names[cols[j]][-2:]], -float(null[j])))
        drop = cols[worst]
        keep[drop] = False
        removed.append(names[drop])
        confounded[names[drop]] = tuple(names[c] for c, v in zip(cols, null.tolist()) if v > 0.1 and c != drop)
    kept = tuple(n for n, k in zip(names, keep) if k)
    return Identifiability(kept=kept, unobservable=tuple(removed), confounded=confounded, singular_values=singular_all)


@dataclass(frozen=True)
class StiffnessEstimate:
    """Identified joint stiffness.

    Attributes:
        names: fitted parameter names (``k_j{i}_{tx..rz}``).
        stiffness: ``(K,)`` estimates, N/m (translations) or N m/rad (rotations).
        relative_std: ``(K,)`` standard deviation of ``log k`` (~ relative std of ``k``),
            scaled by the posterior noise; ``inf`` at the rigid bound.
        covariance_log: ``(K, K)`` covariance of ``log k``.
        identifiability: the structural analysis (what was removed and why).
        at_bound: names that went to the rigid end of :data:`STIFFNESS_BOUNDS`.
        poorly_determined: fitted names with ``relative_std`` above the threshold.
        compliance: ``(N, 6, 6)`` joint compliance for prediction (removed entries rigid).
        model, x: the error model (instrument frame registered) and geometry used.
        rms_residual_m: RMS of the 3-D position residual, m.
        sigma_ratio: posterior / prior noise (about 1 when the noise model fits).
        jacobian_singular_values: of the column-normalized scaled Jacobian at the solution.
        iterations, converged: LM outcome.
    """

    names: tuple[str, ...]
    stiffness: torch.Tensor
    relative_std: torch.Tensor
    covariance_log: torch.Tensor
    identifiability: Identifiability
    at_bound: tuple[str, ...]
    poorly_determined: tuple[str, ...]
    compliance: torch.Tensor
    model: ErrorModel
    x: torch.Tensor
    rms_residual_m: float
    sigma_ratio: float
    jacobian_singular_values: torch.Tensor
    iterations: int
    converged: bool
    with_rotation: bool = False
    wrench_frame: WrenchFrame = "tool"
    extra: dict = field(default_factory=dict)

    def stiffness_by_name(self) -> dict[str, float]:
        return {n: float(k) for n, k in zip(self.names, self.stiffness)}

    def observable(self) -> tuple[str, ...]:
        """Fitted names that are neither at the rigid bound nor poorly determined."""
        bad = set(self.at_bound) | set(self.poorly_determined)
        return tuple(n for n in self.names if n not in bad)

    def predict(self, q: torch.Tensor, wrench: torch.Tensor) -> torch.Tensor:
        """Predicted deflection ``(..., 6)`` ``[dp (m); dphi (rad)]``, ``instrument`` frame."""
        frame = self.wrench_frame
        return deflection(self.model, q, self.x, self.compliance, wrench, wrench_frame=frame)

    def as_dict(self) -> dict:
        """JSON-ready summary (SI units)."""
        return {
            "stiffness": self.stiffness_by_name(),
            "relative_std": {n: float(s) for n, s in zip(self.names, self.relative_std)},
            "unobservable": list(self.identifiability.unobservable),
            "confounded": {k: list(v) for k, v in self.identifiability.confounded.items()},
            "at_bound": list(self.at_bound),
            "poorly_determined": list(self.poorly_determined),
            "rms_residual_mm": self.rms_residual_m * 1e3,
            "sigma_ratio": self.sigma_ratio,
            "iterations": self.iterations,
            "converged": self.converged,
            "with_rotation": self.with_rotation,
            "T_instrument_base": self.model.T_reference.tolist(),
        }


def _bounds(names: Sequence[str], device) -> tuple[torch.Tensor, torch.Tensor]:
    lo = [math.log(STIFFNESS_BOUNDS[n[-2]][0]) for n in names]
    hi = [math.log(STIFFNESS_BOUNDS[n[-2]][1]) for n in names]
    return torch.tensor(lo, dtype=torch.float64, device=device), torch.tensor(hi, dtype=torch.float64, device=device)


def _nonnegative_start(g: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Global minimum of the convex ``|G c - y|`` over ``c >= 0`` (NNLS), the LM start.

    The log-parameterized problem is not convex; started from the non-negative linear optimum
    LM only polishes it and provides the covariance.
    """
    from scipy.optimize import nnls

    norms = g.norm(dim=0).clamp_min(1e-300)
    scaled, _ = nnls((g / norms).cpu().numpy(), y.cpu().numpy(), maxiter=50 * g.shape[1])
    return torch.as_tensor(scaled, dtype=torch.float64, device=g.device) / norms


def _levenberg_marquardt(
    g: torch.Tensor, y: torch.Tensor, s0: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, max_iterations: int, ftol: float
) -> tuple[torch.Tensor, int, bool]:
    """Minimize ``|G exp(-s) - y|^2 / 2`` over box-bounded ``s`` (Marquardt scaling, Nielsen damping)."""

    def evaluate(s):
        c = torch.exp(-s)
        r = g @ c - y
        return r, -g * c

    s = s0.clamp(lo, hi)
    r, jac = evaluate(s)
    cost = 0.5 * float(r @ r)
    jtj = jac.T @ jac
    diag = jtj.diagonal().clamp_min(1e-300)
    lam, nu = 1e-3 * float(diag.max()), 2.0
    converged = False
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 (read after the loop)
        grad = jac.T @ r
        diag = torch.maximum(diag, jtj.diagonal())
        step = torch.linalg.solve(jtj + lam * torch.diag(diag), -grad)
        s_new = (s + step).clamp(lo, hi)
        step = s_new - s
        r_new, jac_new = evaluate(s_new)
        cost_new = 0.5 * float(r_new @ r_new)
        predicted = -float(step @ grad) - 0.5 * float(step @ (jtj @ step))
        rho = (cost - cost_new) / predicted if predicted > 0 else -1.0
        if cost_new < cost:
            decrease = (cost - cost_new) / max(cost, 1e-300)
            s, r, jac, cost = s_new, r_new, jac_new, cost_new
            jtj = jac.T @ jac
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3) if rho > 0 else 1.0
            nu = 2.0
            if decrease < ftol:
                converged = True
                break
        else:
            lam *= nu
            nu *= 2.0
            if float(step.abs().max()) < 1e-12:
                converged = True
                break
    return s, iterations, converged


def identify_stiffness(
    robot: RobotModel | ErrorModel,
    data: StiffnessData,
    *,
    x: torch.Tensor | None = None,
    parameters: str | Sequence[str] = "classic",
    use_rotation: bool | None = None,
    sigma_position_m: float = DEFAULT_SIGMA_POSITION_M,
    sigma_rotation_rad: float = DEFAULT_SIGMA_ROTATION_RAD,
    wrench_frame: WrenchFrame = "tool",
    max_iterations: int = 100,
    ftol: float = 1e-12,
    rank_tol: float = 1e-7,
    poor_relative_std: float = 0.25,
    warn: bool = True,
    device: str | torch.device = "cpu",
) -> StiffnessEstimate:
    """Identify joint stiffness from measured deflections under known wrenches.

    Args:
        robot: nominal robot (or an error model whose robot is used).
        data: the stiffness experiment (see :func:`torchcal.instruments.stiffness.data.load_stiffness`).
        x: calibrated geometry (error-layer vector); nominal by default.
        parameters: ``"classic"`` (``k_j{i}_rz``), ``"full"`` (6-D diagonal, observable part) or
            explicit names.
        use_rotation: fit the rotation columns too (default: when ``data`` has them).
        sigma_position_m / sigma_rotation_rad: noise of one deflection component, for weighting
            and the covariance.
        rank_tol: normalized singular value below which a direction is unobservable.
        poor_relative_std: relative std above which a fitted parameter is reported as poorly
            determined.
        warn: emit :class:`IdentifiabilityWarning` for removed / poorly determined parameters.
    """
    model, x = instrument_model(robot, data, x, device=device)
    n = model.robot.dof
    candidates = resolve_parameters(parameters, n)
    with_rotation = data.rotation is not None if use_rotation is None else bool(use_rotation)
    if with_rotation and data.rotation is None:
        raise DataError("use_rotation=True but the file has no drx, dry, drz columns", path=data.path)
    q, wrench = data.q.to(device), data.wrench.to(device)
    g = stiffness_regressor(model, q, x, wrench, candidates, with_rotation=with_rotation, wrench_frame=wrench_frame)
    rows = 6 if with_rotation else 3
    inverse_sigma = [1.0 / sigma_position_m] * 3 + [1.0 / sigma_rotation_rad] * 3
    weights = torch.tensor(inverse_sigma, dtype=torch.float64, device=device)[:rows]
    y = data.deflection.to(device)
    if with_rotation:
        assert data.rotation is not None  # refused above
        y = torch.cat([y, data.rotation.to(device)], -1)
    gw = (g * weights[:, None]).reshape(-1, len(candidates))
    yw = (y * weights).reshape(-1)

    ident = analyse_identifiability(gw, candidates, rank_tol=rank_tol)
    if not ident.kept:
        raise DataError("no stiffness parameter is observable from this file", path=data.path)
    cols = [candidates.index(nm) for nm in ident.kept]
    gk = gw[:, cols]
    lo, hi = _bounds(ident.kept, device)
    s0 = -torch.log(_nonnegative_start(gk, yw).clamp_min(1e-300))
    s, iterations, converged = _levenberg_marquardt(gk, yw, s0, lo, hi, max_iterations, ftol)

    c = torch.exp(-s)
    r = gk @ c - yw
    jac = -gk * c
    dof_left = max(gk.shape[0] - len(cols), 1)
    sigma_ratio = math.sqrt(float(r @ r) / dof_left)
    at_bound_mask = s >= hi - 1e-9
    free = ~at_bound_mask
    cov = torch.full((len(cols), len(cols)), math.nan, dtype=torch.float64, device=device)
    rel = torch.full((len(cols),), math.inf, dtype=torch.float64, device=device)
    if bool(free.any()):
        jf = jac[:, free]
        cov_f = sigma_ratio**2 * torch.linalg.pinv(jf.T @ jf)
        idx = free.nonzero().squeeze(-1)
        cov[idx[:, None], idx[None, :]] = cov_f
        rel[idx] = cov_f.diagonal().clamp_min(0).sqrt()
    jn = jac / jac.norm(dim=0).clamp_min(1e-300)
    at_bound = tuple(nm for nm, b in zip(ident.kept, at_bound_mask.tolist()) if b)
    poor = tuple(nm for nm, v, b in zip(ident.kept, rel.tolist(), at_bound_mask.tolist()) if not b and v > poor_relative_std)

    compliance = torch.zeros(n, 6, 6, dtype=torch.float64, device=device)
    for nm, ci in zip(ident.kept, c):
        i, k = _parse_name(nm, n)
        compliance[i, k, k] = ci
    pos_res = (r.reshape(-1, rows)[:, :3] / weights[:3]).norm(dim=-1)
    if warn and ident.unobservable:
        details = "; ".join(
            nm
            + (f" (confounded with {', '.join(ident.confounded[nm])})" if ident.confounded.get(nm) else " (no effect)")
            for nm in ident.unobservable
        )
        warnings.warn(
            f"stiffness parameters not observable from {'positions and rotations' if with_rotation else 'TCP positions'}, "
            f"treated as rigid: {details}",
            IdentifiabilityWarning,
            stacklevel=2,
        )
    if warn and poor:
        warnings.warn(
            f"stiffness parameters poorly determined (relative std > {poor_relative_std:g}): {', '.join(poor)}",
            IdentifiabilityWarning,
            stacklevel=2,
        )
    return StiffnessEstimate(
        names=ident.kept,
        stiffness=torch.exp(s),
        relative_std=rel,
        covariance_log=cov,
        identifiability=ident,
        at_bound=at_bound,
        poorly_determined=poor,
        compliance=compliance,
        model=model,
        x=x,
        rms_residual_m=float(pos_res.pow(2).mean().sqrt()),
        sigma_ratio=sigma_ratio,
        jacobian_singular_values=torch.linalg.svdvals(jn),
        iterations=iterations,
        converged=converged,
        with_rotation=with_rotation,
        wrench_frame=wrench_frame,
    )


def deflection_metrics(estimate: StiffnessEstimate, data: StiffnessData) -> dict[str, float]:
    """``deflection_rms_mm`` (measured vs predicted, 3-D) and ``deflection_measured_rms_mm``.

    ``data`` is expressed in the estimate's instrument frame (same set-up); register a new
    set-up with :func:`instrument_model` first.
    """
    pred = estimate.predict(data.q.to(estimate.x.device), data.wrench.to(estimate.x.device))[:, :3]
    meas = data.deflection.to(pred)
    err = (pred - meas).norm(dim=-1)
    return {
        "n_poses": len(data),
        "deflection_rms_mm": float(err.pow(2).mean().sqrt()) * 1e3,
        "deflection_max_mm": float(err.max()) * 1e3,
        "deflection_measured_rms_mm": float(meas.norm(dim=-1).pow(2).mean().sqrt()) * 1e3,
    }
