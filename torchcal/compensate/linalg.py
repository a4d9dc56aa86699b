"""Small dense linear algebra for the exported graphs: two ways to solve the compensator's 6x6 systems.

``torch.linalg.solve`` and ``torch.linalg.inv`` have no standard ONNX export. The systems of the
compensator are symmetric positive definite (``J J^T + lambda^2 I``), which leaves two choices:

* :func:`ort_inverse`: one node of onnxruntime's contrib operator ``com.microsoft.Inverse`` (LU
  with partial pivoting). The default: the compensator is deployed with onnxruntime, and one node
  replaces ``7 n`` elementwise ones per solve, which is most of the graph's latency.
* :func:`gauss_jordan`: elimination without pivoting, written as a Python loop over the constant
  matrix size and unrolled at export into ``7 n`` standard elementwise nodes, for runtimes without
  the contrib domain (``torchcal export --portable``). It is stable on SPD matrices: their diagonal
  pivots stay positive through the elimination (each one is a ratio of leading principal minors).

The position-first steps solve 3x3 systems: :func:`ort_inverse` again, or the closed-form
adjugate :func:`inverse3` (built on :func:`cross`, which the Jacobian of
:mod:`torchcal.compensate.chain` uses too).
"""

from __future__ import annotations

import torch

CONTRIB_DOMAIN = "com.microsoft"
"""ONNX domain of onnxruntime's contrib operators (``Inverse`` lives there, version 1)."""


class _Inverse(torch.autograd.Function):
    """``torch.linalg.inv`` in eager mode, exported as one ``com.microsoft.Inverse`` node."""

    @staticmethod
    def forward(ctx, a: torch.Tensor) -> torch.Tensor:
        return torch.linalg.inv(a)

    @staticmethod
    def symbolic(g, a):
        out = g.op(f"{CONTRIB_DOMAIN}::Inverse", a)
        out.setType(a.type())  # same shape and dtype as the input: the exporter cannot infer a contrib op's
        return out


def ort_inverse(a: torch.Tensor) -> torch.Tensor:
    """Inverse of square matrices ``(..., n, n)``, exportable as onnxruntime's ``Inverse`` node.

    The exported graph then needs onnxruntime (export with ``custom_opsets={CONTRIB_DOMAIN: 1}``).
    No gradient: the graphs that use it are evaluated, never trained.
    """
    return _Inverse.apply(a)


def ort_solve(a: torch.Tensor, rhs: torch.Tensor, eye: torch.Tensor | None = None) -> torch.Tensor:
    """Solve ``a X = rhs`` (``a`` ``(..., n, n)`` invertible, ``rhs`` ``(..., n, k)``) by :func:`ort_inverse`.

    ``eye`` is accepted for a signature shared with :func:`gauss_jordan` and not used.
    """
    return ort_inverse(a) @ rhs


def gauss_jordan(a: torch.Tensor, rhs: torch.Tensor, eye: torch.Tensor | None = None) -> torch.Tensor:
    """Solve ``a X = rhs`` for SPD ``a`` ``(..., n, n)`` and ``rhs`` ``(..., n, k)``; returns ``X``.

    No pivoting (see module docstring): callers must pass a positive definite ``a``. ``eye``:
    an ``(n, n)`` identity to use (a module buffer keeps it a constant of the exported graph).
    """
    n = a.shape[-1]
    g = torch.cat([a, rhs], -1)
    if eye is None:
        eye = torch.eye(n, dtype=a.dtype, device=a.device)
    for k in range(n):
        row = g[..., k : k + 1, :] / g[..., k : k + 1, k : k + 1]
        # Row k becomes the normalized pivot row, every other row loses its column-k entry.
        g = g - (g[..., :, k : k + 1] - eye[:, k : k + 1]) * row
    return g[..., :, n:]


def spd_inverse(a: torch.Tensor) -> torch.Tensor:
    """Inverse of SPD matrices ``(..., n, n)`` by :func:`gauss_jordan`."""
    eye = torch.eye(a.shape[-1], dtype=a.dtype, device=a.device)
    return gauss_jordan(a, eye.expand_as(a))


def cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a x b`` along the last axis (length 3), by index permutations (ONNX has no cross operator)."""
    i1, i2 = [1, 2, 0], [2, 0, 1]
    return a[..., i1] * b[..., i2] - a[..., i2] * b[..., i1]


def inverse3(a: torch.Tensor) -> torch.Tensor:
    """Inverse of invertible ``(..., 3, 3)`` matrices by the adjugate.

    With columns ``c0, c1, c2`` of ``a``, the rows of ``a^-1`` are ``c1 x c2``, ``c2 x c0`` and
    ``c0 x c1`` divided by ``det a = c0 . (c1 x c2)``.
    """
    c0, c1, c2 = a[..., :, 0], a[..., :, 1], a[..., :, 2]
    r0, r1, r2 = cross(c1, c2), cross(c2, c0), cross(c0, c1)
    det = (c0 * r0).sum(-1, keepdim=True).unsqueeze(-1)
    return torch.stack([r0, r1, r2], -2) / det
