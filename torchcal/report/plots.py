"""Plots of position errors before and after calibration (PNG, written atomically)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from torchcal.core.io import atomic_write_bytes


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    atomic_write_bytes(path, buffer.getvalue())


def error_histogram(errors_mm: dict[str, np.ndarray], path: str | Path, title: str) -> Path:
    """Overlaid histograms of 3-D error magnitudes (mm), one per stage."""
    plt = _figure()
    fig, ax = plt.subplots(figsize=(7, 4))
    top = max(float(np.percentile(v, 99.5)) for v in errors_mm.values())
    bins = np.linspace(0, top * 1.05, 50)
    for label, values in errors_mm.items():
        rms = float(np.sqrt(np.mean(values**2)))
        ax.hist(values, bins=bins, alpha=0.55, label=f"{label} (RMS {rms:.3f} mm)")
    ax.set_xlabel("3-D position error [mm]")
    ax.set_ylabel("poses")
    ax.set_title(title)
    ax.legend()
    _save(fig, Path(path))
    plt.close(fig)
    return Path(path)


def per_pose_errors(errors_mm: dict[str, np.ndarray], path: str | Path, title: str) -> Path:
    """3-D error of every test pose, per stage (log scale: stages differ by orders of magnitude)."""
    plt = _figure()
    fig, ax = plt.subplots(figsize=(9, 4))
    for label, values in errors_mm.items():
        ax.plot(np.arange(len(values)), values, ".", ms=3, label=label)
    ax.set_yscale("log")
    ax.set_xlabel("test pose")
    ax.set_ylabel("3-D position error [mm]")
    ax.set_title(title)
    ax.legend()
    _save(fig, Path(path))
    plt.close(fig)
    return Path(path)


def convergence(history: list[float], path: str | Path) -> Path:
    """Solver cost per iteration."""
    plt = _figure()
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.semilogy(np.arange(len(history)), np.asarray(history) * 2, "o-")
    ax.set_xlabel("accepted iteration")
    ax.set_ylabel("sum of squared residuals [m^2]")
    ax.set_title("identification convergence")
    _save(fig, Path(path))
    plt.close(fig)
    return Path(path)
