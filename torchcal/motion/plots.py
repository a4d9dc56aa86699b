"""PNG plots of a motion run (matplotlib, Agg backend): path error, joint speeds, singularity.

Each function takes per-method series (a dict ``label -> arrays``) so that methods compare on one
figure, shades the singular neighbourhood, and writes the PNG atomically.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np

_DEG = 180.0 / math.pi


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _shade(ax, t: np.ndarray, inside: np.ndarray | None) -> None:
    if inside is None or not inside.any():
        return
    ax.fill_between(t, 0, 1, where=inside, transform=ax.get_xaxis_transform(), color="0.85", label="sigma_min < eps")


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".png", dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)
    return path


def plot_path_error(
    t: np.ndarray, errors_mm: dict[str, np.ndarray], path: str | Path, inside: np.ndarray | None = None, limit_mm: float | None = None
) -> Path:
    """Position path error (mm, log scale) against time (s) per method."""
    plt = _figure()
    fig, ax = plt.subplots(figsize=(8, 4))
    _shade(ax, t, inside)
    for label, err in errors_mm.items():
        ax.semilogy(t, np.maximum(err, 1e-9), label=label)
    if limit_mm is not None:
        ax.axhline(limit_mm, color="k", ls="--", lw=0.8, label=f"{limit_mm:g} mm")
    ax.set(xlabel="time [s]", ylabel="TCP position error [mm]", title="Path error")
    ax.legend(fontsize=8)
    out = _save(fig, path)
    plt.close(fig)
    return out


def plot_joint_speeds(
    t: np.ndarray, qdot: dict[str, np.ndarray], limits_rad_s: np.ndarray, path: str | Path, inside: np.ndarray | None = None
) -> Path:
    """Joint speeds normalised by their limits (one panel per method; 1 = at the limit)."""
    plt = _figure()
    fig, axes = plt.subplots(len(qdot), 1, figsize=(8, 2.6 * len(qdot)), sharex=True, squeeze=False)
    for ax, (label, values) in zip(axes[:, 0], qdot.items()):
        _shade(ax, t, inside)
        ratio = np.abs(values) / limits_rad_s
        for j in range(values.shape[-1]):
            ax.plot(t, ratio[:, j], lw=1, label=f"q{j + 1}")
        ax.axhline(1.0, color="k", ls="--", lw=0.8)
        peak = ratio.max()
        if peak > 5:
            ax.set_yscale("log")
            ax.set_ylim(bottom=1e-3)
        ax.set(ylabel="|q_dot| / limit", title=f"{label}: peak {peak:.3g} x limit")
        ax.legend(fontsize=7, ncol=6)
    axes[-1, 0].set_xlabel("time [s]")
    out = _save(fig, path)
    plt.close(fig)
    return out


def plot_singularity(
    t: np.ndarray, sigma_min: np.ndarray, manipulability: np.ndarray, eps: float, path: str | Path
) -> Path:
    """Smallest singular value and manipulability of the Jacobian against time."""
    plt = _figure()
    fig, ax = plt.subplots(figsize=(8, 3.5))
    _shade(ax, t, sigma_min < eps)
    ax.semilogy(t, np.maximum(sigma_min, 1e-12), label="sigma_min")
    ax.semilogy(t, np.maximum(manipulability, 1e-12), label="manipulability")
    ax.axhline(eps, color="k", ls="--", lw=0.8, label=f"eps = {eps:g}")
    ax.set(xlabel="time [s]", ylabel="value", title="Distance to singularity")
    ax.legend(fontsize=8)
    out = _save(fig, path)
    plt.close(fig)
    return out
