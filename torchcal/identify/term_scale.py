"""A stored model's joint-space terms, each scaled as a whole, refitted with the geometry.

A model's joint-space terms (gravity compliance, first joint harmonics;
:mod:`torchcal.identify.joint_errors`) are joint deflections ``dq_t(q)`` added to the commanded
joints. After the robot's life changed something (a payload or balancer changed the gravity sag,
a gearbox was replaced), a few new poses cannot re-identify every coefficient, but they can say
whether a term as a whole still holds: ``q_eff = q + sum_t (1 + s_t) dq_t(q)`` with one scale
``s_t`` per term (0: as stored, -1: gone). :class:`TermScaleProblem` is the least-squares problem
over the geometric parameters and those scales, its Jacobian analytic: the column of ``s_t`` is
the position Jacobian's ``theta_j`` columns weighted by ``dq_t``'s joint ``j``. Residuals in the
instrument frame (m), optionally scaled per pose (whitening by a predicted sigma).
"""

from __future__ import annotations

import torch

from torchcal.data.measurements import Measurements
from torchcal.identify.joint_columns import position_and_columns
from torchcal.kinematics.error_model import ErrorModel


class TermScaleProblem:
    """Least squares over ``[x (P), s (T)]``: geometry plus one scale per joint-space term.

    ``terms (T, n, N)``: each term's deflection at the commanded joints ``data.q`` (rad);
    ``weights (n,)``: per-pose factor on the residual rows (``1 / sigma``; ``None``: 1);
    ``term_names``: the name of each scale.
    """

    rows_per_pose = 3

    def __init__(self, model: ErrorModel, data: Measurements, terms: torch.Tensor, free: torch.Tensor,
                 term_names: list[str], weights: torch.Tensor | None = None) -> None:
        self.model, self.data, self.terms, self.free = model, data, terms, free
        self.term_names, self.weights = term_names, weights
        self.size = model.layout.size

    @property
    def names(self) -> list[str]:
        geo = self.model.layout.names
        return [geo[i] if i < self.size else self.term_names[i - self.size] for i in self.free.tolist()]

    def joints(self, xe: torch.Tensor) -> torch.Tensor:
        """The effective joints ``(n, N)`` rad at the scales in ``xe``."""
        scales = 1.0 + xe[self.size :].to(self.terms)
        return self.data.q + (scales[:, None, None] * self.terms).sum(0)

    def _weigh(self, rows: torch.Tensor) -> torch.Tensor:
        if self.weights is None:
            return rows
        return rows * self.weights.to(rows).reshape(-1, *([1] * (rows.dim() - 1)))

    def residuals(self, xe: torch.Tensor) -> torch.Tensor:
        predicted = self.model.tcp_position(self.joints(xe), xe[: self.size])
        return self._weigh(self.data.position - predicted).reshape(-1)

    def jacobian(self, xe: torch.Tensor, columns: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        columns = self.free if columns is None else columns
        pred, full = position_and_columns(
            self.model, self.joints(xe), xe[: self.size], columns, self.size,
            lambda i, jac_theta: (jac_theta * self.terms[i][:, None, :].to(jac_theta)).sum(-1))
        r = self._weigh(self.data.position - pred).reshape(-1)
        return r, -self._weigh(full).reshape(-1, full.shape[-1])

    def with_free(self, free: torch.Tensor) -> TermScaleProblem:
        return TermScaleProblem(self.model, self.data, self.terms, free, self.term_names, self.weights)
