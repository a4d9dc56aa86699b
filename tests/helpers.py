"""Helpers shared by the tests (one place; ``tests/`` is on the path of every test module).

Central finite differences, the independent check of analytic Jacobians, and small files written
for a test.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import torch


def central_difference_jacobian(residuals: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor,
                                columns: Iterable[int], step: float = 1e-7) -> torch.Tensor:
    """``d residuals / d x[columns]`` ``(M, len(columns))`` by central differences of ``step``."""
    out = []
    for i in columns:
        plus, minus = x.clone(), x.clone()
        plus[i] += step
        minus[i] -= step
        out.append((residuals(plus) - residuals(minus)) / (2 * step))
    return torch.stack(out, -1)


def roundoff_atol(magnitude: float, step: float = 1e-7) -> float:
    """Absolute error a central difference of ``step`` can carry from float64 round-off alone.

    A residual ``measured - predicted`` is the difference of two numbers of about ``magnitude``
    (here the positions in the instrument frame, m), each rounded to ``eps * magnitude``; dividing
    by ``2 step`` turns that into ``eps * magnitude / step`` per entry. A factor 10 covers the
    chain of products before the subtraction.
    """
    return 10 * torch.finfo(torch.float64).eps * magnitude / step


def central_difference(f: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """``d f / d x`` ``(..., len(x))`` by central differences of ``eps`` over every entry of ``x``."""
    return central_difference_jacobian(f, x, range(x.shape[0]), step=eps)


def write_file(folder: Path, text: str, name: str = "m.csv") -> Path:
    """``text`` written to ``folder / name``; returns the path."""
    path = Path(folder) / name
    path.write_text(text)
    return path
