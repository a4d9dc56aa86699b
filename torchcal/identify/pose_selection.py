"""Choosing the most informative experiments: one greedy optimal-design loop, three criteria.

Each candidate ``i`` contributes ``J_i^T J_i`` to the information matrix ``M`` (``J_i`` its
``r x p`` noise-weighted Jacobian). Starting from ``M_0`` (a small ridge, plus the information of
any candidates already chosen), each step adds the candidate with the best gain:

* ``"D"``: ``log det(M + J_i^T J_i) - log det M = log det S_i``, ``S_i = I_r + J_i M^-1 J_i^T``
  (matrix determinant lemma);
* ``"A"``: the drop of ``trace(M^-1)``, the summed parameter variance;
* ``"worst"``: the drop of ``max diag(M^-1)``, the worst parameter variance.

For A and worst the updated inverse follows from Woodbury,
``(M + J^T J)^-1 = M^-1 - B^T S^-1 B`` with ``B = J M^-1``, so the gains of all candidates come
from ``r x r`` solves, evaluated at once. Candidates can be grouped (one pose under several
loads, say): at most one member of a group is chosen.
"""

from __future__ import annotations

from typing import Literal

import torch

from torchcal.data.measurements import Measurements
from torchcal.identify.identifiability import analyze
from torchcal.identify.problem import CalibrationProblem
from torchcal.kinematics.error_model import ErrorModel

Criterion = Literal["D", "A", "worst"]
CRITERIA = ("D", "A", "worst")


def design_criterion(information: torch.Tensor, criterion: Criterion) -> float:
    """Value of ``criterion`` for an information matrix ``(p, p)``; lower is better for all three.

    ``D``: ``-log det M``; ``A``: ``trace(M^-1)``; ``worst``: ``max diag(M^-1)``.
    """
    if criterion == "D":
        return -float(torch.logdet(information))
    inverse_diag = torch.linalg.inv(information).diagonal()
    if criterion == "A":
        return float(inverse_diag.sum())
    if criterion == "worst":
        return float(inverse_diag.max())
    raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")


def _gains(js: torch.Tensor, info: torch.Tensor, criterion: Criterion) -> torch.Tensor:
    """Gain ``(C,)`` of adding each candidate ``(C, r, p)`` to ``info`` (higher is better)."""
    inv = torch.linalg.inv(info)
    b = js @ inv  # (C, r, p)
    s = torch.eye(js.shape[1], dtype=js.dtype, device=js.device) + b @ js.transpose(-1, -2)
    if criterion == "D":
        return torch.logdet(s)
    drop = (b * torch.linalg.solve_ex(s, b)[0]).sum(-2)  # (C, p): diag(B^T S^-1 B); S is SPD
    if criterion == "A":
        return drop.sum(-1)
    # worst: the current worst variance minus the new worst one
    return inv.diagonal().max() - (inv.diagonal() - drop).max(-1).values


def greedy_design(
    jacobians: torch.Tensor,
    k: int,
    *,
    criterion: Criterion = "D",
    initial: torch.Tensor | list[int] | None = None,
    groups: torch.Tensor | None = None,
    prior_information: torch.Tensor | None = None,
    ridge: float = 1e-9,
) -> torch.Tensor:
    """Indices ``(k,)`` of candidates chosen greedily for ``criterion``, ``initial`` ones first.

    Args:
        jacobians: ``(C, r, p)`` noise-weighted Jacobian of each candidate (r rows, p parameters).
        k: total number to choose (``initial`` included).
        criterion: ``"D"``, ``"A"`` or ``"worst"`` (see the module docstring).
        initial: indices already chosen (they count towards ``k``).
        groups: ``(C,)`` integer group of each candidate; once one member is chosen the others
            are no longer available. Default: every candidate its own group.
        prior_information: ``(p, p)`` information known before the design (default: none).
        ridge: added to the diagonal of ``M_0`` so that the first steps are defined; keep it
            small against one candidate's information.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    if jacobians.dim() != 3:
        raise ValueError(f"jacobians must be (candidates, rows, parameters), got shape {tuple(jacobians.shape)}")
    count, _, p = jacobians.shape
    device = jacobians.device
    group = torch.arange(count, device=device) if groups is None else groups.to(device)
    if group.shape != (count,):
        raise ValueError(f"groups must have shape ({count},), got {tuple(group.shape)}")
    chosen = [] if initial is None else [int(i) for i in initial]
    if k > int(torch.unique(group).numel()):
        raise ValueError(f"cannot select {k} poses from {int(torch.unique(group).numel())} candidates")
    if len(chosen) > k:
        raise ValueError(f"{len(chosen)} initial candidates but only {k} to choose")
    info = ridge * torch.eye(p, dtype=jacobians.dtype, device=device)
    if prior_information is not None:
        info = info + prior_information.to(info)
    available = torch.ones(count, dtype=torch.bool, device=device)
    if chosen:
        picked = jacobians[chosen].reshape(-1, p)
        info = info + picked.T @ picked
        available &= ~torch.isin(group, group[chosen])
    while len(chosen) < k:
        gain = _gains(jacobians, info, criterion)
        gain[~available] = -torch.inf
        best = int(torch.argmax(gain))
        chosen.append(best)
        available &= group != group[best]
        info = info + jacobians[best].T @ jacobians[best]
    return torch.tensor(chosen, dtype=torch.long, device=device)


def select_poses_d_optimal(
    jacobians: torch.Tensor,
    k: int,
    *,
    seed_count: int | None = None,
    generator: torch.Generator | None = None,
    ridge: float = 1e-9,
) -> torch.Tensor:
    """Indices of ``k`` poses chosen from candidates' Jacobians ``(C, r, p)`` (r rows per pose).

    Columns are scaled to a common size first (D-optimality does not depend on it, the ridge
    does), then ``seed_count`` random poses start the greedy D-optimal design.
    """
    count, rows, p = jacobians.shape
    if k > count:
        raise ValueError(f"cannot select {k} poses from {count} candidates")
    scale = jacobians.reshape(-1, p).norm(dim=0).clamp_min(1e-300) / count**0.5
    js = jacobians / scale
    seed_count = seed_count if seed_count is not None else max(1, -(-p // rows))
    seed_count = min(seed_count, k)
    initial = torch.randperm(count, generator=generator)[:seed_count]
    return greedy_design(js, k, criterion="D", initial=initial, ridge=ridge).cpu()


def select_poses_for_robot(robot, candidates_q: torch.Tensor, k: int, *, generator: torch.Generator | None = None) -> torch.Tensor:
    """Pick ``k`` of the candidate joint vectors ``(C, N)`` (rad) that best identify ``robot``.

    The information matrix is that of the identifiable parameter set at the nominal model; it
    does not depend on where the instrument stands (a rotation of the rows leaves ``J^T J`` alone).
    """
    model = ErrorModel(robot)
    x = model.nominal_vector()
    free = torch.nonzero(model.default_active()).squeeze(-1)
    problem = CalibrationProblem(model, Measurements(q=candidates_q, position=robot.tcp_position(candidates_q)), free)
    _, jac = problem.jacobian(x)
    report = analyze(jac, problem.names)
    keep = [problem.names.index(n) for n in report.base_set]
    per_pose = jac.reshape(candidates_q.shape[0], 3, -1)[:, :, keep]
    return select_poses_d_optimal(per_pose, k, generator=generator)
