"""Modified Denavit-Hartenberg (Craig) link transforms with the Hayati ``beta`` extension.

One link transform from frame ``i-1`` to frame ``i``::

    T = Rx(alpha_{i-1}) Tx(a_{i-1}) Ry(beta_{i-1}) Rz(theta_i + q_i) Tz(d_i)

With ``beta = 0`` this is Craig's modified DH. ``beta`` (Hayati) tilts axis ``i`` about the
y axis of the intermediate frame; it is what stays well conditioned when axes ``i-1`` and ``i``
are nearly parallel, where a tiny misalignment would otherwise need a huge ``d``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcal.kinematics.transforms import broadcast_shapes


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
    shape = broadcast_shapes(ca.shape, cb.shape, ct.shape, a.shape, d.shape)
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


@dataclass(frozen=True)
class ChainFrames:
    """Every frame of one forward pass through an MDH+beta chain, in the frame the chain starts in.

    Each field is a tuple with one entry per joint ``i = 1..N``; every entry is a vector stored
    component-major, ``(3, ...)`` (component first, then the batch): elementwise kernels then
    broadcast per-pose scalars along contiguous memory, several times faster than ``(..., 3)``
    rows times a ``(..., 1)`` scalar. Entries may carry size-1 batch dims where they do not
    depend on the pose yet. These are the axes and points of the screw-form parameter Jacobian
    (:mod:`torchcal.kinematics.param_jacobian`, which runs the same recursion in place).

    Attributes:
        x_prev: axis ``x_{i-1}`` of frame ``i-1`` (the ``alpha`` axis, the ``a`` direction).
        o_prev: origin ``o_{i-1}`` of frame ``i-1`` (on the ``alpha`` axis).
        y_mid: ``y`` axis of the intermediate frame after ``Rx(alpha) Tx(a)`` (the ``beta`` axis).
        m_mid: origin of that intermediate frame, ``o_{i-1} + a x_{i-1}`` (on the ``beta`` axis).
        x, y, z: axes of frame ``i`` (``z_i`` is joint ``i``'s axis).
        o: origin ``o_i`` of frame ``i`` (on the joint axis).
    """

    x_prev: tuple[torch.Tensor, ...]
    o_prev: tuple[torch.Tensor, ...]
    y_mid: tuple[torch.Tensor, ...]
    m_mid: tuple[torch.Tensor, ...]
    x: tuple[torch.Tensor, ...]
    y: tuple[torch.Tensor, ...]
    z: tuple[torch.Tensor, ...]
    o: tuple[torch.Tensor, ...]

    def stacked(self, name: str) -> torch.Tensor:
        """Field ``name`` as one ``(..., N, 3)`` tensor (rows, joint on dim ``-2``)."""
        entries = getattr(self, name)
        shape = broadcast_shapes(*(v.shape for v in entries))
        return torch.stack([v.expand(shape) for v in entries], -1).movedim(0, -1)


def _fields(q: torch.Tensor, table: torch.Tensor, nb: int) -> tuple[tuple[torch.Tensor, ...], ...]:
    """Per-joint ``a, d`` and sines/cosines of ``alpha, beta, theta + q``, each padded to ``nb`` batch dims.

    With the joint index leading, each joint's per-pose values are one contiguous block.
    """
    n = q.shape[-1]
    fields = table.movedim(-1, 0).movedim(-1, 1).contiguous()
    alpha, a, beta, theta0, d = fields.reshape(5, n, *([1] * (nb + 2 - table.dim())), *table.shape[:-2])
    angle = theta0 + q.movedim(-1, 0).reshape(n, *([1] * (nb + 1 - q.dim())), *q.shape[:-1])
    ca, sa, cb, sb = torch.cos(alpha), torch.sin(alpha), torch.cos(beta), torch.sin(beta)
    ct, st = torch.cos(angle), torch.sin(angle)
    # unbind once: indexing per joint inside the loop costs a dispatch each (visible at small batch)
    return tuple(v.unbind(0) for v in (a, d, ca, sa, -sa, cb, sb, -sb, ct, st, -st))


def to_components(v: torch.Tensor, batch_ndim: int) -> torch.Tensor:
    """``(..., 3)`` -> ``(3, ...)`` padded with leading unit dims to ``1 + batch_ndim`` dims (a view)."""
    v = v.movedim(-1, 0)
    return v.reshape(3, *([1] * (batch_ndim - (v.dim() - 1))), *v.shape[1:])


def _propagate(
    q: torch.Tensor,
    table: torch.Tensor,
    r_start: torch.Tensor | None,
    p_start: torch.Tensor | None,
    record: bool,
) -> tuple[tuple[torch.Tensor, ...], list[tuple[torch.Tensor, ...]]]:
    """Walk the chain rotating the accumulated frame's columns by the elementary rotations.

    Each link is ``Rx(alpha) Tx(a) Ry(beta) Rz(theta + q) Tz(d)``; right-multiplying a frame by
    an elementary rotation mixes two of its axis vectors, so a link costs a dozen fused
    multiply-adds on ``(3, ...)`` tensors instead of a 3x3 ``bmm`` per pose (dominated by
    per-matrix overhead at large batch). Sines and cosines of ``alpha`` and ``beta`` are
    computed once per table; ``theta + q`` once for all joints. Vectors are ``(3, ...)``.
    """
    batch = broadcast_shapes(q.shape[:-1], table.shape[:-2])
    nb = len(batch)
    a, d, ca, sa, nsa, cb, sb, nsb, ct, st, nst = _fields(q, table, nb)
    if r_start is None:
        eye = torch.eye(3, dtype=q.dtype, device=q.device).reshape(3, 3, *([1] * nb))
        x, y, z = eye[:, 0], eye[:, 1], eye[:, 2]
    else:
        x, y, z = (to_components(r_start[..., :, k], nb) for k in range(3))
    if p_start is None:
        o = torch.zeros((3,) + (1,) * nb, dtype=q.dtype, device=q.device)
    else:
        o = to_components(p_start, nb)
    records: list[tuple[torch.Tensor, ...]] = []
    for i in range(q.shape[-1]):
        x_prev, o_prev = x, o
        m = torch.addcmul(o, a[i], x)
        # Rx(alpha): y, z rotate about x.
        y, z = torch.addcmul(ca[i] * y, sa[i], z), torch.addcmul(ca[i] * z, nsa[i], y)
        y_mid = y
        # Ry(beta): z, x rotate about y (Hayati tilt).
        x, z = torch.addcmul(cb[i] * x, nsb[i], z), torch.addcmul(cb[i] * z, sb[i], x)
        # Rz(theta + q): x, y rotate about the joint axis z.
        c = ct[i]
        x, y = torch.addcmul(c * x, st[i], y), torch.addcmul(c * y, nst[i], x)
        o = torch.addcmul(m, d[i], z)
        if record:
            records.append((x_prev, o_prev, y_mid, m, x, y, z, o))
    return (x, y, z, o), records


def chain_frames(
    q: torch.Tensor,
    table: torch.Tensor,
    *,
    r_start: torch.Tensor | None = None,
    p_start: torch.Tensor | None = None,
) -> ChainFrames:
    """All joint frames of an MDH+beta chain, expressed in the frame ``(r_start, p_start)``.

    Args:
        q: ``(..., N)`` joint angles, rad.
        table: ``(..., N, 5)`` rows ``[alpha, a, beta, theta_offset, d]`` (rad, length unit).
        r_start: ``(..., 3, 3)`` rotation of MDH frame 0 in the output frame (identity if None).
        p_start: ``(..., 3)`` origin of MDH frame 0 in the output frame (zero if None).

    Returns:
        :class:`ChainFrames` (per-joint, component-major ``(3, ...)`` vectors).
    """
    _, records = _propagate(q, table, r_start, p_start, record=True)
    return ChainFrames(*(tuple(f) for f in zip(*records)))


def _rows(v: torch.Tensor, batch: torch.Size) -> torch.Tensor:
    """Component-major ``(3, ...)`` -> contiguous ``(..., 3)``."""
    return v.expand(3, *batch).movedim(0, -1).contiguous()


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
    batch = broadcast_shapes(q.shape[:-1], table.shape[:-2])
    if all_frames:
        f = chain_frames(q, table)
        rot = torch.stack([f.stacked("x"), f.stacked("y"), f.stacked("z")], -1)
        return rot.expand(*batch, q.shape[-1], 3, 3).contiguous(), f.stacked("o").expand(*batch, q.shape[-1], 3).contiguous()
    (x, y, z, o), _ = _propagate(q, table, None, None, record=False)
    rot = torch.stack([v.expand(3, *batch) for v in (x, y, z)], -1).movedim(0, -2)
    return rot.contiguous(), _rows(o, batch)


def chain_point(
    q: torch.Tensor,
    table: torch.Tensor,
    point: torch.Tensor,
    *,
    r_start: torch.Tensor | None = None,
    p_start: torch.Tensor | None = None,
) -> torch.Tensor:
    """Position ``(..., 3)`` of ``point`` (``(..., 3)``, given in frame N) in frame 0 (or the start frame).

    The hot path of TCP positions. Only a point is needed, so the chain is walked from the tip
    to the base applying each link to the point's three coordinates (``(...)`` tensors):
    ``Tz(d)``, ``Rz(theta + q)``, ``Ry(beta)``, ``Tx(a)``, ``Rx(alpha)``. That is about 14
    scalar-array ops per link, a third of the memory traffic of propagating a frame.

    Args:
        q: ``(..., N)`` joint angles, rad.
        table: ``(..., N, 5)`` MDH+beta rows (rad, length unit).
        point: ``(..., 3)`` point in frame N (same length unit).
        r_start, p_start: optional ``(..., 3, 3)`` / ``(..., 3)`` pose of frame 0 in an outer
            frame; the result is then expressed in that frame.
    """
    batch = broadcast_shapes(q.shape[:-1], table.shape[:-2])
    a, d, ca, sa, nsa, cb, sb, nsb, ct, st, nst = _fields(q, table, len(batch))
    vx, vy, vz = point.unbind(-1)
    for i in range(q.shape[-1] - 1, -1, -1):
        vz = vz + d[i]
        c, s = ct[i], st[i]
        vx, vy = torch.addcmul(c * vx, nst[i], vy), torch.addcmul(c * vy, s, vx)
        vx, vz = torch.addcmul(cb[i] * vx, sb[i], vz), torch.addcmul(cb[i] * vz, nsb[i], vx)
        vx = vx + a[i]
        vy, vz = torch.addcmul(ca[i] * vy, nsa[i], vz), torch.addcmul(ca[i] * vz, sa[i], vy)
    if r_start is not None:
        r = r_start
        out = [
            torch.addcmul(torch.addcmul(r[..., k, 0] * vx, r[..., k, 1], vy), r[..., k, 2], vz)
            for k in range(3)
        ]
        vx, vy, vz = out if p_start is None else (out[k] + p_start[..., k] for k in range(3))
    elif p_start is not None:
        vx, vy, vz = vx + p_start[..., 0], vy + p_start[..., 1], vz + p_start[..., 2]
    shape = broadcast_shapes(vx.shape, vy.shape, vz.shape)
    return torch.stack([vx.expand(shape), vy.expand(shape), vz.expand(shape)], -1)


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
