"""Residuals of pooled measurement series, each series after its own rigid frame (variable projection).

Poses of several series (:mod:`torchcal.data.series`) share the robot but not the instrument
placement. For the series after the first, the rigid frame is projected out of the least-squares
problem: at each evaluation the series' points are registered onto the prediction in closed form
(Kabsch, the frame's exact optimum for these parameters) and the Jacobian rows of the series are
projected onto the complement of the six rigid motions of its predicted points (Kaufman's
variable projection). The solver then minimises the cost over the robot's parameters with every
series' frame at its optimum, without frame parameters of its own; the first series' frame stays
the model's instrument frame. A single series (``data.series`` ``None`` or one value) is untouched.
"""

from __future__ import annotations

import torch

from torchcal.data.measurements import Measurements
from torchcal.kinematics.transforms import rigid_registration


def _rigid_columns(points: torch.Tensor) -> torch.Tensor:
    """``(3n, 6)``: how the points move under a translation ``v`` and a small rotation ``w`` (``v + w x p``)."""
    n = points.shape[0]
    g = torch.zeros(n, 3, 6, dtype=points.dtype, device=points.device)
    g[:, :, :3] = torch.eye(3, dtype=points.dtype, device=points.device)
    x, y, z = points.unbind(-1)
    zero = torch.zeros_like(x)
    # w x p = -[p]x w
    g[:, :, 3:] = -torch.stack([torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1),
                                torch.stack([-y, x, zero], -1)], -2)
    return g.reshape(3 * n, 6)


def per_series_registered(data: Measurements, r: torch.Tensor,
                          jac: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Position residuals ``r`` ``(3n,)`` (``measured - predicted``, m) and their Jacobian ``(3n, K)``
    with each series after the first registered onto the prediction (see the module docstring).

    The registered residual of a series is its measured points mapped by the optimal frame minus
    the prediction (reference frame, m); its norm is the series' misfit after that frame alone.
    """
    if data.series is None:
        return r, jac
    series = data.series.to(r.device)
    count = int(series.max()) + 1
    if count < 2:
        return r, jac
    r = r.clone()
    jac = None if jac is None else jac.clone()
    measured = data.position.to(r)
    for s in range(1, count):
        rows = torch.nonzero(series == s).squeeze(-1)
        flat = (rows.unsqueeze(-1) * 3 + torch.arange(3, device=r.device)).reshape(-1)
        p = measured[rows]
        predicted = p - r[flat].reshape(-1, 3)
        t = rigid_registration(predicted, p)
        r[flat] = ((p - t[:3, 3]) @ t[:3, :3] - predicted).reshape(-1)
        if jac is not None:
            g = _rigid_columns(predicted)
            block = jac[flat]
            jac[flat] = block - g @ torch.linalg.solve(g.T @ g, g.T @ block)
    return r, jac


def held_out_errors(predict, train: Measurements, test: Measurements) -> torch.Tensor:
    """``test.position - predict(test.q)`` ``(n, 3)`` (m), each later series of ``test`` first mapped by its
    frame registered on the fold's training poses of that series (``predict(q) -> (k, 3)``: the fold
    fit's prediction, reference frame): a fold fit placed every series' frame itself, so its
    held-out poses are scored in that frame, found without them."""
    predicted = predict(test.q)
    errors = test.position.to(predicted) - predicted
    if test.series is None or train.series is None:
        return errors
    for s in torch.unique(test.series).tolist():
        rows, known = torch.nonzero(test.series == s).squeeze(-1), torch.nonzero(train.series == s).squeeze(-1)
        if s == 0 or len(known) < 3:
            continue
        t = rigid_registration(predict(train.q[known]), train.position[known].to(predicted))
        errors[rows] = (test.position[rows].to(predicted) - t[:3, 3]) @ t[:3, :3] - predicted[rows]
    return errors
