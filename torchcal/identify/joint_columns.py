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
    theta = torch.tensor([model.layout.index(f"theta{j + 1}") for j in range(model.robot.dof)])
    geo = columns[columns < size]
    pose, jac = model.pose_jacobian(q, x, torch.cat([geo, theta]))
    jac_geo, jac_theta = jac[..., : len(geo)], jac[..., len(geo) :]
    parts, g = [], 0
    for col in columns.tolist():
        if col < size:
            parts.append(jac_geo[..., g])
            g += 1
        else:
            parts.append(joint_column(col - size, jac_theta))
    return pose, torch.stack(parts, -1)


def position_and_columns(model: ErrorModel, q: torch.Tensor, x: torch.Tensor, columns: torch.Tensor, size: int,
                         joint_column: Callable[[int, torch.Tensor], torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Predicted TCP positions ``(B, 3)`` (m) at joints ``q`` (rad) and the Jacobian ``(B, 3, len(columns))``.

    A column index below ``size`` is a geometric parameter of ``x``; index ``size + i`` is joint-space
    coefficient ``i``, whose column ``joint_column(i, jac_theta)`` combines the ``theta_j`` columns
    ``jac_theta`` ``(B, 3, N)`` into ``(B, 3)``.
    """
    theta = torch.tensor([model.layout.index(f"theta{j + 1}") for j in range(model.robot.dof)])
    geo = columns[columns < size]
    pred, jac = model.position_jacobian(q, x, torch.cat([geo, theta]), method="analytic")
    jac_geo, jac_theta = jac[..., : len(geo)], jac[..., len(geo) :]
    parts, g = [], 0
    for col in columns.tolist():
        if col < size:
            parts.append(jac_geo[..., g])
            g += 1
        else:
            parts.append(joint_column(col - size, jac_theta))
    return pred, torch.stack(parts, -1)
