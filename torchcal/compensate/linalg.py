"""Small dense linear algebra written as a fixed sequence of tensor operations.

``torch.linalg.solve`` and ``torch.linalg.inv`` have no ONNX export, and the 6x6 systems of the
compensator are symmetric positive definite (``J J^T + lambda^2 I``), so Gauss-Jordan elimination
without pivoting is stable on them: the diagonal pivots of an SPD matrix stay positive through
the elimination (each one is a ratio of leading principal minors). The loop over the matrix size
is a Python loop over a constant, unrolled at export into ``7 n`` elementwise ONNX nodes.
"""

from __future__ import annotations

import torch


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
