"""Jacobian columns of a fit whose unknowns are geometry and joint-space coefficients.

A joint-space coefficient moves the TCP through the joint angles: its column is a combination of
the ``theta_j`` columns of the position Jacobian (``dP/dc = sum_j dP/dtheta_j * dq_j/dc``). The
geometric and the ``theta`` columns come from one analytic Jacobian.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcal.kinematics.error_model import ErrorModel


def pose_and_columns(model: ErrorModel, q: torch.Tensor, x: torch.Tensor, columns: torch.Tensor, size: int,
                     joint_column: Callable[[int, torch.Tensor], torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """TCP pose ``(B, 4, 4)`` at joints ``q`` (rad) and the Jacobian ``(B, 6, len(columns))`` of
    ``[p, rotation vector]`` (m, rad; :meth:`~torchcal.kinematics.error_model.ErrorModel.pose_jacobian`),
    the joint-space columns made as in :func:`position_and_columns` from the ``theta_j`` columns ``(B, 6, N)``."""
    geo, theta = _geometric_and_theta(model, columns, size)
    pose, jac = model.pose_jacobian(q, x, torch.cat([geo, theta]))
    return pose, _assembled(jac, columns, size, len(geo), joint_column)


def position_and_columns(model: ErrorModel, q: torch.Tensor, x: torch.Tensor, columns: torch.Tensor, size: int,
                         joint_column: Callable[[int, torch.Tensor], torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Predicted TCP positions ``(B, 3)`` (m) at joints ``q`` (rad) and the Jacobian ``(B, 3, len(columns))``.

    A column index below ``size`` is a geometric parameter of ``x``; index ``size + i`` is joint-space
    coefficient ``i``, whose column ``joint_column(i, jac_theta)`` combines the ``theta_j`` columns
    ``jac_theta`` ``(B, 3, N)`` into ``(B, 3)``.
    """
    geo, theta = _geometric_and_theta(model, columns, size)
    pred, jac = model.position_jacobian(q, x, torch.cat([geo, theta]), method="analytic")
    return pred, _assembled(jac, columns, size, len(geo), joint_column)


def _geometric_and_theta(model: ErrorModel, columns: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The geometric columns among ``columns`` and the indices of every joint offset ``theta_j``."""
    theta = torch.tensor([model.layout.index(f"theta{j + 1}") for j in range(model.robot.dof)])
    return columns[columns < size], theta


def _assembled(jac: torch.Tensor, columns: torch.Tensor, size: int, n_geo: int,
               joint_column: Callable[[int, torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """``jac`` ``(B, R, n_geo + N)`` (the geometric columns, then the ``theta_j`` ones) as the columns of ``columns``."""
    jac_geo, jac_theta = jac[..., :n_geo], jac[..., n_geo:]
    parts, g = [], 0
    for col in columns.tolist():
        if col < size:
            parts.append(jac_geo[..., g])
            g += 1
        else:
            parts.append(joint_column(col - size, jac_theta))
    return torch.stack(parts, -1)
