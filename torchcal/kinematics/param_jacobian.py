"""Analytic Jacobian of the TCP position with respect to every calibration parameter.

Screw form: a parameter that rotates the distal part of the chain about a line (unit axis
``w`` through a point ``c``) moves the TCP ``p`` by ``w x (p - c)`` per rad; one that
translates it along ``w`` moves it by ``w`` per m. With the link transform
``Rx(alpha) Tx(a) Ry(beta) Rz(theta + q) Tz(d)`` of joint ``i`` (see
:mod:`torchcal.kinematics.mdh`), all vectors in the ``instrument`` frame:

=========  ==========================================  ======================================
parameter  motion of everything after it                column ``dp / d param``
=========  ==========================================  ======================================
alpha{i}   rotation about ``x_{i-1}`` through ``o_{i-1}``  ``x_{i-1} x (p - o_{i-1})``
a{i}       translation along ``x_{i-1}``               ``x_{i-1}``
beta{i}    rotation about ``y_mid`` through ``m``      ``y_mid x (p - m)``, ``m = o_{i-1} + a x_{i-1}``
theta{i}   rotation about ``z_i`` through ``o_i``      ``z_i x (p - o_i)``
d{i}       translation along ``z_i``                   ``z_i``
=========  ==========================================  ======================================

``y_mid`` is the ``y`` axis after ``Rx(alpha)`` (``Ry(beta)`` turns about it). The base
correction enters as ``T_instrument_base = T_reference [exp(r), t]``; its translation columns
are the columns of ``R_reference``, and its rotation-vector columns are exact at any ``r`` (not
only at zero) through the right Jacobian of SO(3)::

    d/dr exp(r) v = -exp(r) [v]_x J_r(r),  J_r(r) = I - (1 - cos t)/t^2 [r]_x + (t - sin t)/t^3 [r]_x^2

so column ``k`` is ``M[:, k] x (p - c_base)`` with ``M = R_reference exp(r) J_r(r)`` and
``c_base`` the corrected base origin. Tool columns are the columns of ``R_instrument_flange``;
the tool-rotation columns are zero (a point has no orientation).

Every column comes from the frames of one forward pass (the recursion of
:func:`~torchcal.kinematics.mdh.chain_frames`, run in place on blocks of poses), batched,
without autograd: one to two orders of magnitude faster than reverse-mode autodiff with
per-pose parameter copies (see docs/bench_kinematics.md). The autodiff Jacobian
(``ErrorModel.position_jacobian(method="autodiff")``) stays the reference it is tested
against, together with central finite differences.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics import transforms as tf

if TYPE_CHECKING:  # the model calls into this module; the type only is needed here
    from torchcal.kinematics.error_model import ErrorModel

__all__ = ["so3_right_jacobian", "tcp_position_jacobian"]


def so3_right_jacobian(rotvec: torch.Tensor) -> torch.Tensor:
    """Right Jacobian ``J_r (..., 3, 3)`` of SO(3) at rotation vector ``rotvec (..., 3)``, rad.

    ``exp(r + dr) = exp(r) exp(J_r(r) dr) + O(|dr|^2)``. Taylor form below ``|r| = 1e-4`` rad,
    where the closed form loses digits to cancellation.
    """
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True).unsqueeze(-1)
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(safe2)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    c = torch.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - torch.sin(theta)) / (safe2 * theta))
    k = tf.skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(k)
    return eye - b * k + c * (k @ k)


def _column_index(columns: torch.Tensor | None, size: int) -> list[int]:
    if columns is None:
        return list(range(size))
    columns = torch.as_tensor(columns)
    if columns.dtype == torch.bool:
        if columns.shape != (size,):
            raise ModelError(f"columns mask has shape {tuple(columns.shape)}, expected ({size},)")
        columns = columns.nonzero().squeeze(-1)
    index = [int(c) for c in columns.reshape(-1).tolist()]
    bad = [c for c in index if not -size <= c < size]
    if bad:
        raise ModelError(f"columns {bad} are outside the {size} parameters")
    return [c % size for c in index]


def _empty(shape: tuple[int, ...], like: torch.Tensor) -> torch.Tensor:
    """Uninitialised tensor; on CPU backed by a NumPy buffer.

    NumPy asks the kernel for transparent huge pages on large buffers; torch's CPU allocator
    does not, and first-touch page faults of a fresh 100 MB Jacobian otherwise cost more than
    computing it.
    """
    if like.device.type == "cpu":
        np_dtype = torch.empty(0, dtype=like.dtype).numpy().dtype
        return torch.from_numpy(np.empty(shape, dtype=np_dtype))
    return torch.empty(shape, dtype=like.dtype, device=like.device)


def _cross_into(out: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> None:
    """``out (3, n) = u x v`` for vectors in the extended layout ``(5, n)`` (see :class:`_Workspace`).

    Rows ``1:4`` and ``2:5`` of the extended layout are the cyclic shifts ``(u1, u2, u0)`` and
    ``(u2, u0, u1)``, so the cross product is two kernels on contiguous slices.
    """
    torch.mul(u[1:4], v[2:5], out=out).addcmul_(u[2:5], v[1:4], value=-1.0)


_EXTEND = [0, 1, 2, 0, 1]


class _Workspace:
    """Frames of one block of poses, written in place, in the extended component-major layout.

    A vector is stored as ``(5, n)`` rows ``(v0, v1, v2, v0, v1)``: every step of the recursion
    is linear, so it runs on the extra rows unchanged, and cross products become two kernels on
    row slices (:func:`_cross_into`). ``x, y, z, o`` hold frames ``0..N`` (entry 0: MDH frame 0
    in the instrument frame); ``y_mid, m_mid`` the ``beta`` axis and its point per joint.

    The same recursion as :func:`torchcal.kinematics.mdh.chain_frames`, specialised to one
    shared parameter vector (link constants as Python floats) and to ``out=`` kernels: nothing is
    allocated inside the loop over blocks, where allocator traffic (mmap, page faults) would
    cost as much as the arithmetic. Per-joint views are made once and reused by every block.
    """

    def __init__(self, n_joints: int, n: int, like: torch.Tensor) -> None:
        self.n = n
        frames = _empty((4, n_joints + 1, 5, n), like)
        mids = _empty((2, n_joints, 5, n), like)
        self.x, self.y, self.z, self.o = (list(f.unbind(0)) for f in frames.unbind(0))
        self.y_mid, self.m_mid = (list(f.unbind(0)) for f in mids.unbind(0))
        self.z_a, self.x_b, self.p, self.lever = _empty((4, 5, n), like).unbind(0)

    def forward(
        self,
        cos_q: list[torch.Tensor],
        sin_q: list[torch.Tensor],
        rows: list[list[float]],
        start_r: torch.Tensor,
        start_p: torch.Tensor,
        p_n: list[float],
    ) -> None:
        """Fill the frames for per-joint cosines/sines ``(n,)`` of ``theta + q``, and the TCP ``p``."""
        x, y, z, o = self.x, self.y, self.z, self.o
        x[0].copy_(start_r[_EXTEND, 0:1])
        y[0].copy_(start_r[_EXTEND, 1:2])
        z[0].copy_(start_r[_EXTEND, 2:3])
        o[0].copy_(start_p[_EXTEND, None])
        z_a, x_b = self.z_a, self.x_b
        for i, (alpha, a, beta, _, d) in enumerate(rows):
            ca, sa, cb, sb = math.cos(alpha), math.sin(alpha), math.cos(beta), math.sin(beta)
            c, s = cos_q[i], sin_q[i]
            y_mid = self.y_mid[i]
            torch.add(o[i], x[i], alpha=a, out=self.m_mid[i])  # Tx(a)
            torch.mul(y[i], ca, out=y_mid).add_(z[i], alpha=sa)  # Rx(alpha)
            torch.mul(z[i], ca, out=z_a).add_(y[i], alpha=-sa)
            torch.mul(x[i], cb, out=x_b).add_(z_a, alpha=-sb)  # Ry(beta)
            torch.mul(z_a, cb, out=z[i + 1]).add_(x[i], alpha=sb)
            torch.mul(x_b, c, out=x[i + 1]).addcmul_(y_mid, s)  # Rz(theta + q)
            torch.mul(y_mid, c, out=y[i + 1]).addcmul_(x_b, s, value=-1.0)
            torch.add(self.m_mid[i], z[i + 1], alpha=d, out=o[i + 1])  # Tz(d)
        torch.add(o[-1], x[-1], alpha=p_n[0], out=self.p).add_(y[-1], alpha=p_n[1]).add_(z[-1], alpha=p_n[2])


DEFAULT_CHUNK = 4096
"""Poses per block: the block's frames (about 40 vectors of 3 x chunk) stay in cache."""


@torch.no_grad()
def tcp_position_jacobian(
    model: ErrorModel,
    q: torch.Tensor,
    x: torch.Tensor,
    columns: torch.Tensor | None = None,
    *,
    chunk: int = DEFAULT_CHUNK,
) -> tuple[torch.Tensor, torch.Tensor]:
    """TCP positions and their analytic Jacobian with respect to ``x[columns]``.

    Args:
        model: the error layer (its layout and fixed frames).
        q: ``(..., N)`` joint angles, rad.
        x: ``(P,)`` parameter vector shared by all poses (SI units).
        columns: indices (or a ``(P,)`` boolean mask) of the parameters to differentiate
            (default: all, in layout order).
        chunk: poses per block (memory and speed only; results do not depend on it).

    Returns:
        ``(p, J)``: ``p (..., 3)`` TCP in the ``instrument`` frame, m; ``J (..., 3, K)`` in m per
        parameter unit (m/rad for angles, m/m for lengths). Not differentiable (no autograd graph).
    """
    layout = model.layout
    if x.dim() != 1 or x.shape[0] != layout.size:
        raise ModelError(
            f"analytic Jacobian needs one shared parameter vector of {layout.size} entries, got shape {tuple(x.shape)}"
        )
    if q.shape[-1] != layout.n_joints:
        raise ModelError(f"q has {q.shape[-1]} joints, the model has {layout.n_joints}")
    if chunk < 1:
        raise ModelError(f"chunk must be a positive number of poses, got {chunk}")
    x = x.detach()
    lead = q.shape[:-1]
    q = q.detach().reshape(-1, layout.n_joints).to(x)
    batch = q.shape[0]
    index = _column_index(columns, layout.size)
    n_cols = len(index)

    # Pose-independent pieces, once.
    base = x[layout.base_slice]
    r_ref, t_ref = model.T_reference[:3, :3].to(x), model.T_reference[:3, 3].to(x)
    c_base = (r_ref @ base[:3] + t_ref)[_EXTEND, None]  # corrected base origin, instrument frame
    base_axes = (r_ref @ tf.so3_exp(base[3:]) @ so3_right_jacobian(base[3:]))[_EXTEND]
    world = model.instrument_from_0(x)
    world_r, world_p = world[:3, :3], world[:3, 3]
    table = model.table(x)
    rows = table.tolist()
    p_n = model.tool_in_n(x).tolist()
    r_nf = model.T_n_flange[:3, :3].to(x).tolist()
    n_table = 5 * layout.n_joints
    base_start, tool_start = layout.base_slice.start, layout.tool_slice.start
    # theta + q for all poses, joint-major so that each joint's row is contiguous
    angle = (q + table[:, 3]).T.contiguous()
    cos_q, sin_q = torch.cos(angle).unbind(0), torch.sin(angle).unbind(0)

    p_out = _empty((batch, 3), x)
    jac = _empty((batch, 3, n_cols), x)
    # Columns are written into blk (3, K, n), pose index last: contiguous elementwise writes.
    # Viewed as (3K, n) its transpose is exactly the block's (n, 3, K) rows of the result, a
    # plain 2-D transpose that torch copies with its blocked kernel.
    ws: _Workspace | None = None  # and blk, cols: allocated with it, on the first block
    for start in range(0, batch, chunk):
        n = min(chunk, batch - start)
        if ws is None or ws.n != n:  # first block, and the last if shorter
            ws = _Workspace(layout.n_joints, n, x)
            blk = _empty((3, n_cols, n), x)
            cols = blk.unbind(1)
        span = slice(start, start + n)
        ws.forward([c[span] for c in cos_q], [s[span] for s in sin_q], rows, world_r, world_p, p_n)
        p, lever = ws.p, ws.lever
        for k, col in enumerate(index):
            out = cols[k]
            if col < n_table:
                joint, field = divmod(col, 5)
                if field == 0:  # alpha: about x_{i-1} through o_{i-1}
                    _cross_into(out, ws.x[joint], torch.sub(p, ws.o[joint], out=lever))
                elif field == 1:  # a: along x_{i-1}
                    out.copy_(ws.x[joint][:3])
                elif field == 2:  # beta: about y_mid through m
                    _cross_into(out, ws.y_mid[joint], torch.sub(p, ws.m_mid[joint], out=lever))
                elif field == 3:  # theta: about z_i through o_i
                    _cross_into(out, ws.z[joint + 1], torch.sub(p, ws.o[joint + 1], out=lever))
                else:  # d: along z_i
                    out.copy_(ws.z[joint + 1][:3])
            elif col < base_start + 3:  # base translation: columns of R_reference
                out.copy_(r_ref[:, col - base_start, None])
            elif col < tool_start:  # base rotation vector: about M[:, k] through the base origin
                _cross_into(out, base_axes[:, col - base_start - 3, None], torch.sub(p, c_base, out=lever))
            elif col < tool_start + 3:  # tool point: columns of R_instrument_flange
                j = col - tool_start
                torch.mul(ws.x[-1][:3], r_nf[0][j], out=out).add_(ws.y[-1][:3], alpha=r_nf[1][j]).add_(
                    ws.z[-1][:3], alpha=r_nf[2][j]
                )
            else:  # tool rotation does not move a point
                out.zero_()
        jac[span].view(n, 3 * n_cols).copy_(blk.view(3 * n_cols, n).T)
        p_out[span].copy_(p[:3].T)
    return p_out.reshape(*lead, 3), jac.reshape(*lead, 3, n_cols)
