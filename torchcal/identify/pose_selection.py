"""Choosing the most informative poses: greedy D-optimal design.

Starting from ``seed_count`` random poses, each step adds the candidate that maximizes
``det(M + J_i^T J_i)`` where ``M`` is the current (column-scaled) information matrix. By the
matrix determinant lemma this is ``det(I_3 + J_i M^-1 J_i^T)``, evaluated for all candidates at
once.
"""

from __future__ import annotations

import torch


def select_poses_d_optimal(
    jacobians: torch.Tensor,
    k: int,
    *,
    seed_count: int | None = None,
    generator: torch.Generator | None = None,
    ridge: float = 1e-9,
) -> torch.Tensor:
    """Indices of ``k`` poses chosen from candidates' Jacobians ``(C, r, p)`` (r rows per pose)."""
    count, rows, p = jacobians.shape
    if k > count:
        raise ValueError(f"cannot select {k} poses from {count} candidates")
    scale = jacobians.reshape(-1, p).norm(dim=0).clamp_min(1e-300) / count**0.5
    js = jacobians / scale
    seed_count = seed_count if seed_count is not None else max(1, -(-p // rows))
    seed_count = min(seed_count, k)
    chosen = torch.randperm(count, generator=generator)[:seed_count].tolist()
    info = js[chosen].reshape(-1, p).T @ js[chosen].reshape(-1, p) + ridge * torch.eye(p, dtype=js.dtype)
    available = torch.ones(count, dtype=torch.bool)
    available[chosen] = False
    eye = torch.eye(rows, dtype=js.dtype)
    while len(chosen) < k:
        inv = torch.linalg.inv(info)
        gain = torch.logdet(eye + js @ inv @ js.transpose(-1, -2))
        gain[~available] = -torch.inf
        best = int(torch.argmax(gain))
        chosen.append(best)
        available[best] = False
        info = info + js[best].T @ js[best]
    return torch.tensor(chosen, dtype=torch.long)


def select_poses_for_robot(robot, candidates_q: torch.Tensor, k: int, *, generator: torch.Generator | None = None) -> torch.Tensor:
    """Pick ``k`` of the candidate joint vectors ``(C, N)`` (rad) that best identify ``robot``.

    The information matrix is that of the identifiable parameter set at the nominal model; it
    does not depend on where the instrument stands (a rotation of the rows leaves ``J^T J`` alone).
    """
    from torchcal.data.measurements import Measurements
    from torchcal.identify.identifiability import analyze
    from torchcal.identify.problem import CalibrationProblem
    from torchcal.kinematics.error_model import ErrorModel

    model = ErrorModel(robot)
    x = model.nominal_vector()
    free = torch.nonzero(model.default_active()).squeeze(-1)
    problem = CalibrationProblem(model, Measurements(q=candidates_q, position=robot.tcp_position(candidates_q)), free)
    _, jac = problem.jacobian(x)
    report = analyze(jac, problem.names)
    keep = [problem.names.index(n) for n in report.base_set]
    per_pose = jac.reshape(candidates_q.shape[0], 3, -1)[:, :, keep]
    return select_poses_d_optimal(per_pose, k, generator=generator)
