"""Figures of a calibration report, each returned as PNG bytes (matplotlib, Agg, no global state).

Conventions: lengths in mm, angles in deg; legends sit outside the data (right of the axes);
axes that count (poses, rows, iterations) have integer ticks.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence

import numpy as np

DPI = 100
#: What drawing a figure imports on first use: a worker that will draw figures imports it ahead
#: (:func:`torchcal.core.workers.import_in_workers`).
IMPORTS = ("torchcal.report.plots", "matplotlib.figure", "matplotlib.backends.backend_agg", "PIL.PngImagePlugin")
#: Colours of the stages, in order (nominal first, the delivered model last).
COLOURS = ("#9e9e9e", "#1f77b4", "#2ca02c", "#d62728", "#9467bd", "#8c564b")


def _figure(width: float, height: float, nrows: int = 1, ncols: int = 1, **kwargs):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False, **kwargs)
    return fig, axes


def _png(fig) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI)
    return buffer.getvalue()


def _integer_axis(axis) -> None:
    from matplotlib.ticker import MaxNLocator

    axis.set_major_locator(MaxNLocator(integer=True))


def _legend_below(fig, ax) -> None:
    """The legend of ``ax`` under the axes, outside the data, long labels wrapped."""
    import textwrap

    handles, labels = ax.get_legend_handles_labels()
    fig.legend(handles, ["\n".join(textwrap.wrap(label, 60)) for label in labels], loc="outside lower center",
               ncols=min(2, len(labels)), fontsize=8, frameon=False)


def _wrap(text: str, width: int = 90) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width))


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if len(values) else math.nan


def error_histogram(errors_mm: dict[str, np.ndarray], title: str) -> bytes:
    """Overlaid histograms of 3-D error magnitudes (mm), one per stage."""
    fig, axes = _figure(8.5, 3.6)
    ax = axes[0, 0]
    top = max(float(np.percentile(v, 99.5)) for v in errors_mm.values())
    bins = np.linspace(0.0, top * 1.05 if top > 0 else 1.0, 40)
    for colour, (label, values) in zip(COLOURS, errors_mm.items()):
        ax.hist(np.clip(values, 0, bins[-1]), bins=bins, alpha=0.55, color=colour, label=f"{label} (RMS {_rms(values):.3f} mm)")
    ax.set_xlabel("3-D position error [mm]")
    ax.set_ylabel("poses")
    _integer_axis(ax.yaxis)
    ax.set_title(title, fontsize=10)
    _legend_below(fig, ax)
    return _png(fig)


def per_pose_errors(rows: Sequence[int] | np.ndarray, errors_mm: dict[str, np.ndarray], title: str) -> bytes:
    """3-D error of every pose against its row in the file, per stage (log scale)."""
    fig, axes = _figure(8.5, 3.6)
    ax = axes[0, 0]
    x = np.asarray(rows)
    for colour, (label, values) in zip(COLOURS, errors_mm.items()):
        ax.plot(x, np.maximum(values, 1e-6), ".", ms=3, color=colour, label=label)
    ax.set_yscale("log")
    ax.set_xlabel("row in the file (header = row 1)")
    ax.set_ylabel("3-D position error [mm]")
    _integer_axis(ax.xaxis)
    ax.set_title(title, fontsize=10)
    _legend_below(fig, ax)
    return _png(fig)


def axis_errors(rows: Sequence[int] | np.ndarray, vectors_mm: np.ndarray, stage: str, title: str) -> bytes:
    """Signed error along x, y and z (mm, instrument frame) of every pose under one model stage."""
    fig, axes = _figure(8.5, 6.0, nrows=3, sharex=True)
    x = np.asarray(rows)
    for k, name in enumerate("xyz"):
        ax = axes[k, 0]
        ax.plot(x, vectors_mm[:, k], ".", ms=3, color=COLOURS[1])
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_ylabel(f"{name} error [mm]")
        ax.set_title(f"{name}: mean {vectors_mm[:, k].mean():+.4f} mm, RMS {_rms(vectors_mm[:, k]):.4f} mm", fontsize=8,
                     loc="right")
    axes[2, 0].set_xlabel("row in the file (header = row 1)")
    _integer_axis(axes[2, 0].xaxis)
    fig.suptitle(_wrap(f"{title}: {stage}"), fontsize=10)
    return _png(fig)


def error_vs_joints(q_deg: np.ndarray, errors_mm: np.ndarray, stage: str, title: str) -> bytes:
    """3-D error of one model stage against each joint angle (deg), one panel per joint, with the median per bin."""
    from matplotlib.ticker import MaxNLocator

    n = q_deg.shape[1]
    cols = 3 if n <= 6 else 4
    nrows = math.ceil(n / cols)
    fig, axes = _figure(9.5, 2.7 * nrows + 0.8, nrows=nrows, ncols=cols, sharey=True)
    for j in range(nrows * cols):
        ax = axes[j // cols, j % cols]
        if j >= n:
            ax.set_visible(False)
            continue
        ax.plot(q_deg[:, j], errors_mm, ".", ms=2, color=COLOURS[1], label="pose")
        edges = np.linspace(q_deg[:, j].min(), q_deg[:, j].max(), 11)
        which = np.clip(np.digitize(q_deg[:, j], edges[1:-1]), 0, len(edges) - 2)
        centres, medians = [], []
        for b in range(len(edges) - 1):
            inside = errors_mm[which == b]
            if len(inside) >= 3:
                centres.append(0.5 * (edges[b] + edges[b + 1]))
                medians.append(float(np.median(inside)))
        ax.plot(centres, medians, "-", color=COLOURS[3], lw=1.5, label="median per tenth of the joint's range")
        ax.xaxis.set_major_locator(MaxNLocator(nbins=4))
        ax.set_xlabel(f"q{j + 1} [deg]")
        if j % cols == 0:
            ax.set_ylabel("3-D error [mm]")
    _legend_below(fig, axes[0, 0])
    fig.suptitle(_wrap(f"{title}: {stage}"), fontsize=10)
    return _png(fig)


def joint_curves(q_deg: np.ndarray, learned_mdeg: np.ndarray, truth_mdeg: np.ndarray | None, title: str,
                 label: str) -> bytes:
    """A learned periodic joint error ``dq_j(q_j)`` (mdeg) against ``q_j`` (deg), one panel per joint, with the
    truth where known; ``q_deg`` ``(M, N)`` sorted per joint, curves ``(M, N)``."""
    from matplotlib.ticker import MaxNLocator

    n = q_deg.shape[1]
    cols = 3 if n <= 6 else 4
    nrows = math.ceil(n / cols)
    fig, axes = _figure(9.5, 2.5 * nrows + 0.8, nrows=nrows, ncols=cols)
    for j in range(nrows * cols):
        ax = axes[j // cols, j % cols]
        if j >= n:
            ax.set_visible(False)
            continue
        if truth_mdeg is not None:
            ax.plot(q_deg[:, j], truth_mdeg[:, j], "-", color=COLOURS[0], lw=2.5, alpha=0.6, label="twin's truth")
        ax.plot(q_deg[:, j], learned_mdeg[:, j], "-", color=COLOURS[3], lw=1.2, label=label)
        ax.xaxis.set_major_locator(MaxNLocator(nbins=4))
        ax.set_xlabel(f"q{j + 1} [deg]")
        if j % cols == 0:
            ax.set_ylabel("joint error [mdeg]")
    _legend_below(fig, axes[0, 0])
    fig.suptitle(_wrap(title), fontsize=10)
    return _png(fig)


def workspace(points_mm: np.ndarray, errors_mm: np.ndarray, title: str, frame: str) -> bytes:
    """The poses' TCP positions seen from above (x-y) and from the side (x-z), coloured by 3-D error (mm)."""
    fig, axes = _figure(9.5, 4.2, ncols=2)
    order = np.argsort(errors_mm)  # largest errors drawn last, on top
    scatter = None
    for ax, (a, b) in zip(axes[0], ((0, 1), (0, 2))):
        scatter = ax.scatter(points_mm[order, a], points_mm[order, b], c=errors_mm[order], s=9, cmap="viridis",
                             vmin=0.0, vmax=float(np.percentile(errors_mm, 99)) or None)
        ax.set_xlabel(f"{'xyz'[a]} [mm]")
        ax.set_ylabel(f"{'xyz'[b]} [mm]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"{'xyz'[a]}-{'xyz'[b]} plane, {frame} frame", fontsize=9)
    assert scatter is not None
    fig.colorbar(scatter, ax=axes[0].tolist(), label="3-D error [mm]", shrink=0.9)
    fig.suptitle(_wrap(title), fontsize=10)
    return _png(fig)


def correlation_heatmap(correlation: np.ndarray, names: Sequence[str]) -> bytes:
    """Correlation matrix of the identified parameters (-1 .. 1)."""
    k = len(names)
    size = min(11.0, max(5.0, 0.28 * k + 2.5))
    fig, axes = _figure(size + 1.2, size)
    ax = axes[0, 0]
    image = ax.imshow(correlation, cmap="RdBu_r", vmin=-1.0, vmax=1.0, interpolation="nearest")
    ax.set_xticks(range(k), labels=list(names), rotation=90, fontsize=7)
    ax.set_yticks(range(k), labels=list(names), fontsize=7)
    ax.set_title("correlation of the identified parameters", fontsize=10)
    fig.colorbar(image, ax=ax, label="correlation coefficient", shrink=0.8)
    return _png(fig)


def predicted_vs_observed(predicted_p95_mm: np.ndarray, observed_mm: np.ndarray, coverage: float) -> bytes:
    """Observed 3-D error of each pose against the 95 % radius the model predicted for it (mm)."""
    fig, axes = _figure(8.0, 4.6)
    ax = axes[0, 0]
    inside = observed_mm <= predicted_p95_mm
    ax.plot(predicted_p95_mm[inside], observed_mm[inside], ".", ms=4, color=COLOURS[1],
            label=f"within the predicted radius ({inside.sum()} poses)")
    ax.plot(predicted_p95_mm[~inside], observed_mm[~inside], ".", ms=4, color=COLOURS[3],
            label=f"outside ({(~inside).sum()} poses)")
    top = float(max(predicted_p95_mm.max(), observed_mm.max())) * 1.05
    ax.plot([0, top], [0, top], "k--", lw=0.8, label="observed = predicted 95 % radius")
    ax.set_xlim(0, top)
    ax.set_ylim(0, top)
    ax.set_xlabel("predicted 95 % radius of the 3-D error [mm]")
    ax.set_ylabel("observed 3-D error [mm]")
    ax.set_title(f"prediction uncertainty: {100 * coverage:.1f} % of the poses inside (95 % expected)", fontsize=10)
    _legend_below(fig, ax)
    return _png(fig)


def convergence(history: Sequence[float]) -> bytes:
    """Solver cost per accepted iteration (sum of squared residuals, mm^2)."""
    fig, axes = _figure(7.0, 3.2)
    ax = axes[0, 0]
    values = np.asarray(history, dtype=np.float64) * 2 * 1e6  # 0.5 r^T r in m^2 -> r^T r in mm^2
    ax.semilogy(np.arange(len(values)), np.maximum(values, 1e-30), "o-", ms=3)
    ax.set_xlabel("accepted iteration")
    ax.set_ylabel("sum of squared residuals [mm²]")
    _integer_axis(ax.xaxis)
    ax.set_title("identification convergence", fontsize=10)
    return _png(fig)
