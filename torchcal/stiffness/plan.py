"""Loading plan for a force rig: which poses to load, and with which wrench (experiment design).

Random wrenches at random poses waste most of the rig: a random moment direction puts on
average a third of its square about the tool axis, and with magnitudes uniform in 0.2..1 of the
limit joint 6's own spring (``k_j6_rz``) gets about 1/7 of the rig's mean-square moment; it is
seen mainly through the probe's rotations, so its sigma suffers most. The plan instead picks,
greedily from candidate poses within the joint limits, one pose at a time and for it one wrench
at the rig's limits (full force, full moment) from a set of ``tool``-frame directions.

Criterion. The identification fits ``s = log k`` by weighted least squares, so the Fisher
information of an experiment is ``M = sum_i J_i^T J_i`` with ``J_i = -W G_i diag(c)`` (``G_i``
the regressor of :func:`~torchcal.stiffness.identify.stiffness_regressor`, ``W`` the inverse
noise std per row, ``c = 1 / k``): the same measurement model and weights as the fit, and
``diag(M^-1)`` are the predicted relative variances of the stiffnesses. It depends on ``k``, which
is unknown before the experiment: the plan is designed at a guess (the middle of the prior
range, say), never at the truth. The default criterion is A-optimality (smallest summed relative
variance); the greedy loop is :func:`torchcal.identify.pose_selection.greedy_design`.

The information does not change when the rows are rotated, so the plan needs no instrument
frame: the nominal model with ``instrument = base`` is enough.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from torchcal.core.errors import DataError
from torchcal.identify.pose_selection import Criterion, design_criterion, greedy_design
from torchcal.kinematics.error_model import ErrorModel
from torchcal.stiffness.identify import (
    DEFAULT_SIGMA_POSITION_M,
    DEFAULT_SIGMA_ROTATION_RAD,
    resolve_parameters,
    stiffness_regressor,
)


def unit_directions() -> torch.Tensor:
    """14 unit vectors ``(14, 3)``: the 6 coordinate axes (both signs) and the 8 cube diagonals."""
    axes = torch.cat([torch.eye(3), -torch.eye(3)]).double()
    signs = torch.tensor([[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)], dtype=torch.float64)
    return torch.cat([axes, signs / math.sqrt(3.0)])


def rig_wrenches(
    max_force_n: float,
    max_torque_nm: float,
    directions: torch.Tensor | None = None,
    *,
    device: str | torch.device = "cpu",
) -> torch.Tensor:
    """Every force direction with every moment direction at the rig's limits, ``(D^2, 6)`` tool frame.

    Args:
        max_force_n / max_torque_nm: force (N) and moment about the TCP (N m) magnitudes.
        directions: ``(D, 3)`` unit vectors in the ``tool`` frame (default :func:`unit_directions`).
    """
    if not (max_force_n >= 0 and max_torque_nm >= 0) or max_force_n + max_torque_nm <= 0:
        raise DataError(f"rig limits must be non-negative and not both zero, got {max_force_n} N and {max_torque_nm} N m")
    d = (unit_directions() if directions is None else directions.to(torch.float64)).to(device)
    if d.dim() != 2 or d.shape[-1] != 3 or not torch.allclose(d.norm(dim=-1), torch.ones(d.shape[0], dtype=d.dtype, device=d.device)):
        raise DataError(f"directions must be unit vectors (D, 3), got shape {tuple(d.shape)}")
    f = d.repeat_interleave(d.shape[0], 0) * max_force_n
    m = d.repeat(d.shape[0], 1) * max_torque_nm
    return torch.cat([f, m], -1)


def _without_opposites(wrenches: torch.Tensor) -> torch.Tensor:
    """Drop ``-w`` where ``w`` is kept: the deflection is linear in the wrench, so both carry the
    same information (to first order) and the search halves."""
    scale = wrenches.abs().max().clamp_min(1e-300)
    opposite = (wrenches[:, None, :] + wrenches[None, :, :]).abs().amax(-1) <= 1e-9 * scale  # (D, D)
    first = torch.where(opposite.any(-1), opposite.float().argmax(-1), torch.arange(len(wrenches), device=wrenches.device))
    return wrenches[first >= torch.arange(len(wrenches), device=wrenches.device)]


def log_stiffness_jacobian(
    model: ErrorModel,
    q: torch.Tensor,
    x: torch.Tensor,
    wrench: torch.Tensor,
    names: Sequence[str],
    stiffness: torch.Tensor,
    *,
    with_rotation: bool = True,
    sigma_position_m: float = DEFAULT_SIGMA_POSITION_M,
    sigma_rotation_rad: float = DEFAULT_SIGMA_ROTATION_RAD,
) -> torch.Tensor:
    """Noise-weighted ``d(deflection)/d(log k)`` ``(..., rows, K)`` at ``stiffness`` ``(K,)``.

    Rows are ``[dp (m); dphi (rad)]`` divided by their noise std (3 rows without rotation);
    ``q`` ``(..., N)`` rad, ``wrench`` ``(..., 6)`` N, N m in the ``tool`` frame.
    """
    g = stiffness_regressor(model, q, x, wrench, names, with_rotation=with_rotation)
    rows = g.shape[-2]
    weights = torch.tensor([1.0 / sigma_position_m] * 3 + [1.0 / sigma_rotation_rad] * 3, dtype=g.dtype, device=g.device)
    compliance = 1.0 / stiffness.to(g)
    return -(g * weights[:rows, None]) * compliance


def predicted_relative_std(jacobian: torch.Tensor) -> torch.Tensor:
    """Std of ``log k`` (~ relative std of ``k``) ``(K,)`` of the experiment ``(B, rows, K)``.

    ``inf`` for a parameter the experiment does not determine.
    """
    k = jacobian.shape[-1]
    j = jacobian.reshape(-1, k)
    info = j.T @ j
    if int(torch.linalg.matrix_rank(info)) < k:
        return torch.full((k,), math.inf, dtype=info.dtype, device=info.device)
    return torch.linalg.inv(info).diagonal().clamp_min(0).sqrt()


@dataclass(frozen=True)
class LoadingPlan:
    """Where and how to load the robot.

    Attributes:
        q: ``(P, N)`` joint angles, rad.
        wrench: ``(P, 6)`` force (N) and moment about the TCP (N m), ``tool`` frame.
        candidate_index: ``(P,)`` index of each pose among the candidate poses.
        names: the stiffness parameters the plan is designed for.
        design_stiffness: ``(K,)`` stiffness the information is evaluated at (N m/rad, N/m).
        relative_std: ``(K,)`` predicted std of ``log k`` at ``design_stiffness``.
        criterion: ``"A"``, ``"D"`` or ``"worst"``; criterion_value: its value (lower is better).
    """

    q: torch.Tensor
    wrench: torch.Tensor
    candidate_index: torch.Tensor
    names: tuple[str, ...]
    design_stiffness: torch.Tensor
    relative_std: torch.Tensor
    criterion: str
    criterion_value: float

    def as_dict(self) -> dict:
        """JSON-ready summary (the poses themselves are in the data file)."""
        return {
            "criterion": self.criterion,
            "criterion_value": self.criterion_value,
            "n_poses": int(self.q.shape[0]),
            "design_stiffness": {n: float(k) for n, k in zip(self.names, self.design_stiffness)},
            "predicted_relative_std_at_design": {n: float(s) for n, s in zip(self.names, self.relative_std)},
        }


def plan_loading(
    model: ErrorModel,
    candidates_q: torch.Tensor,
    n_poses: int,
    design_stiffness: torch.Tensor,
    *,
    x: torch.Tensor | None = None,
    parameters: str | Sequence[str] = "classic",
    max_force_n: float = 300.0,
    max_torque_nm: float = 30.0,
    directions: torch.Tensor | None = None,
    with_rotation: bool = True,
    sigma_position_m: float = DEFAULT_SIGMA_POSITION_M,
    sigma_rotation_rad: float = DEFAULT_SIGMA_ROTATION_RAD,
    criterion: Criterion = "A",
    ridge_fraction: float = 1e-6,
) -> LoadingPlan:
    """Choose ``n_poses`` of the candidate poses and a rig-limit wrench for each.

    Args:
        model: nominal (or calibrated) error model; its instrument frame does not matter.
        candidates_q: ``(C, N)`` joint angles (rad) within the joint limits, away from
            singularities (the plan does not check regularity, only limits).
        n_poses: poses in the plan (each candidate pose is used at most once).
        design_stiffness: ``(K,)`` guess of the stiffness of ``parameters`` (N m/rad, N/m),
            e.g. the middle of the prior range; not the truth.
        x: geometry (error-layer vector); nominal by default.
        parameters: as for :func:`~torchcal.stiffness.identify.identify_stiffness`.
        max_force_n / max_torque_nm / directions: the wrench set, see :func:`rig_wrenches`.
        with_rotation / sigma_position_m / sigma_rotation_rad: the measurement, as in the fit.
        criterion: ``"A"`` (default), ``"D"`` or ``"worst"``.
        ridge_fraction: starting ridge, relative to the mean information of one candidate.
    """
    device = model.T_reference.device
    names = resolve_parameters(parameters, model.robot.dof)
    q = candidates_q.to(device, torch.float64)
    if q.dim() != 2 or q.shape[-1] != model.robot.dof:
        raise DataError(f"candidate poses must be (C, {model.robot.dof}) rad, got shape {tuple(q.shape)}")
    if not bool(model.robot.within_limits(q).all()):
        raise DataError("candidate poses must lie within the joint limits")
    if not 1 <= n_poses <= q.shape[0]:
        raise DataError(f"cannot plan {n_poses} poses from {q.shape[0]} candidates")
    stiffness = torch.as_tensor(design_stiffness, dtype=torch.float64, device=device)
    if stiffness.shape != (len(names),) or not bool((stiffness > 0).all() & torch.isfinite(stiffness).all()):
        raise DataError(f"design_stiffness needs {len(names)} positive finite values, got {stiffness.tolist()}")
    x = model.nominal_vector() if x is None else x.to(device, torch.float64)
    wrenches = _without_opposites(rig_wrenches(max_force_n, max_torque_nm, directions, device=device))

    # The regressor is linear in the wrench: evaluate it once per pose for the 6 unit wrenches.
    count, n_wrench = q.shape[0], wrenches.shape[0]
    unit = torch.eye(6, dtype=torch.float64, device=device).expand(count, 6, 6)
    basis = log_stiffness_jacobian(
        model,
        q.unsqueeze(1).expand(count, 6, q.shape[-1]),
        x,
        unit,
        names,
        stiffness,
        with_rotation=with_rotation,
        sigma_position_m=sigma_position_m,
        sigma_rotation_rad=sigma_rotation_rad,
    )  # (C, 6 unit wrenches, rows, K)
    jac = torch.einsum("cjrk,dj->cdrk", basis, wrenches).reshape(count * n_wrench, basis.shape[-2], len(names))
    groups = torch.arange(count, device=device).repeat_interleave(n_wrench)
    mean_info = float(jac.pow(2).sum((-2, -1)).mean()) / len(names)
    chosen = greedy_design(jac, n_poses, criterion=criterion, groups=groups, ridge=ridge_fraction * mean_info)
    picked = jac[chosen]
    info = picked.reshape(-1, len(names)).T @ picked.reshape(-1, len(names))
    pose_index = chosen // n_wrench
    return LoadingPlan(
        q=q[pose_index],
        wrench=wrenches[chosen % n_wrench],
        candidate_index=pose_index,
        names=names,
        design_stiffness=stiffness,
        relative_std=predicted_relative_std(picked),
        criterion=criterion,
        criterion_value=design_criterion(info, criterion),
    )
