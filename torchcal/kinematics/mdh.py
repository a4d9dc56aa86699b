"""Modified Denavit-Hartenberg (Craig) link transforms with the Hayati ``beta`` extension.

One link transform from frame ``i-1`` to frame ``i``::

    T = Rx(alpha_{i-1}) Tx(a_{i-1}) Ry(beta_{i-1}) Rz(theta_i + q_i) Tz(d_i)

With ``beta = 0`` this is Craig's modified DH. ``beta`` (Hayati) tilts axis ``i`` about the
y axis of the intermediate frame; it is what stays well conditioned when axes ``i-1`` and ``i``
are nearly parallel, where a tiny misalignment would otherwise need a huge ``d``.
"""

from __future__ import annotations

import torch


def link_transform(
    alpha: torch.Tensor,
    a: torch.Tensor,
    beta: torch.Tensor,
    theta: torch.Tensor,
    d: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form rotation ``(..., 3, 3)`` and translation ``(..., 3)`` of one MDH+beta link.

    All arguments broadcast; angles in rad, lengths in any unit (returned in the same unit).
    """
    ca, sa = torch.cos(alpha), torch.sin(alpha)
    cb, sb = torch.cos(beta), torch.sin(beta)
    ct, st = torch.cos(theta), torch.sin(theta)
    shape = torch.broadcast_shapes(ca.shape, cb.shape, ct.shape, a.shape, d.shape)
    ca, sa, cb, sb, ct, st = (x.expand(shape) for x in (ca, sa, cb, sb, ct, st))
    a, d = a.expand(shape), d.expand(shape)
    sasb, casb = sa * sb, ca * sb
    rotation = torch.stack(
        [
            torch.stack([cb * ct, -cb * st, sb], -1),
            torch.stack([sasb * ct + ca * st, -sasb * st + ca * ct, -sa * cb], -1),
            torch.stack([-casb * ct + sa * st, casb * st + sa * ct, ca * cb], -1),
        ],
        -2,
    )
    translation = torch.stack([a + sb * d, -sa * cb * d, ca * cb * d], -1)
    return rotation, translation


def chain_transforms(
    q: torch.Tensor, table: torch.Tensor, *, all_frames: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward kinematics of an MDH+beta chain from frame 0 to frame N.

    Args:
        q: ``(..., N)`` joint angles, rad.
        table: ``(..., N, 5)`` rows ``[alpha, a, beta, theta_offset, d]`` (rad, length unit);
            may carry a batch of its own (one table per pose) for per-pose gradients.
        all_frames: return every frame ``0->i`` stacked on dim ``-3`` instead of only ``0->N``.

    Returns:
        ``(R, p)`` with ``R (..., 3, 3)`` and ``p (..., 3)`` (or ``(..., N, 3, 3)`` / ``(..., N, 3)``).
    """
    alpha, a, beta, theta0, d = table.unbind(-1)
    rot, trans = link_transform(alpha, a, beta, theta0 + q, d)
    r_acc, p_acc = rot[..., 0, :, :], trans[..., 0, :]
    frames_r, frames_p = [r_acc], [p_acc]
    for i in range(1, q.shape[-1]):
        p_acc = p_acc + (r_acc @ trans[..., i, :].unsqueeze(-1)).squeeze(-1)
        r_acc = r_acc @ rot[..., i, :, :]
        if all_frames:
            frames_r.append(r_acc)
            frames_p.append(p_acc)
    if all_frames:
        return torch.stack(frames_r, -3), torch.stack(frames_p, -2)
    return r_acc, p_acc


def decompose_link(transform: torch.Tensor) -> torch.Tensor:
    """Recover ``[alpha, a, beta, theta, d]`` from an exact MDH+beta link transform ``(..., 4, 4)``.

    Inverse of :func:`link_transform` for ``|beta| < pi/2`` and ``cos(beta) != 0``.
    """
    r, p = transform[..., :3, :3], transform[..., :3, 3]
    beta = torch.asin(r[..., 0, 2].clamp(-1.0, 1.0))
    alpha = torch.atan2(-r[..., 1, 2], r[..., 2, 2])
    theta = torch.atan2(-r[..., 0, 1], r[..., 0, 0])
    cb = torch.cos(beta)
    d = (-torch.sin(alpha) * p[..., 1] + torch.cos(alpha) * p[..., 2]) / cb
    a = p[..., 0] - torch.sin(beta) * d
    return torch.stack([alpha, a, beta, theta, d], -1)
