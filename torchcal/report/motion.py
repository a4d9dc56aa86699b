"""The report of ``torchcal motion``: figures and tables of a planned joint trajectory.

Units: mm, deg, s. The figures are PNG bytes (:mod:`torchcal.report.plots` conventions); the
report is a :class:`~torchcal.report.document.Report`, written by ``write_report``.
"""

from __future__ import annotations

import numpy as np

from torchcal.report.document import Figure, Paragraph, Report, Section, Table
from torchcal.report.plots import COLOURS, _figure, _png

_JOINT_COLOURS = (*COLOURS[1:], "#e377c2", "#17becf", "#bcbd22")


def _shade(ax, t: np.ndarray, singular: np.ndarray) -> None:
    if singular.any():
        ax.fill_between(t, 0, 1, where=singular, transform=ax.get_xaxis_transform(), color="0.88",
                        label="singular neighbourhood")


def path_error_figure(t: np.ndarray, position_mm: np.ndarray, orientation_deg: np.ndarray, singular: np.ndarray,
                      tolerance_mm: float) -> bytes:
    """Path error (mm) and orientation deviation (deg) of every sample against time."""
    fig, axes = _figure(8.0, 5.0, 2, 1, sharex=True)
    top, bottom = axes[0, 0], axes[1, 0]
    floor = 1e-12
    _shade(top, t, singular)
    top.semilogy(t, np.maximum(position_mm, floor), color=COLOURS[1], label="path error (floor 1e-12 mm)")
    top.axhline(tolerance_mm, color=COLOURS[3], linestyle="--", label=f"tolerance {tolerance_mm:g} mm")
    top.set_ylabel("path error (mm)")
    top.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, frameon=False)
    _shade(bottom, t, singular)
    bottom.semilogy(t, np.maximum(orientation_deg, floor), color=COLOURS[2], label="orientation deviation")
    bottom.set_ylabel("orientation deviation (deg)")
    bottom.set_xlabel("t (s)")
    bottom.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, frameon=False)
    return _png(fig)


def joint_figure(t: np.ndarray, values: np.ndarray, limits: np.ndarray, singular: np.ndarray, label: str,
                 unit: str) -> bytes:
    """Per-joint series ``(K, N)`` against time with each joint's limit (dashed, both signs)."""
    fig, axes = _figure(8.0, 3.6)
    ax = axes[0, 0]
    _shade(ax, t, singular)
    for j in range(values.shape[1]):
        colour = _JOINT_COLOURS[j % len(_JOINT_COLOURS)]
        ax.plot(t, values[:, j], color=colour, linewidth=1.0, label=f"q{j + 1}")
        for sign in (1.0, -1.0):
            ax.axhline(sign * limits[j], color=colour, linestyle=":", linewidth=0.8)
    lim = max(float(np.max(np.abs(values))) if values.size else 0.0, float(np.max(limits)))
    ax.set_ylim(-1.1 * lim - 1e-9, 1.1 * lim + 1e-9)
    ax.set_xlabel("t (s)")
    ax.set_ylabel(f"{label} ({unit})")
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, frameon=False,
              title="dotted: limits", title_fontsize=8)
    return _png(fig)


def singularity_figure(t: np.ndarray, sigma_orientation: np.ndarray, sigma_position_mm: np.ndarray,
                       eps_orientation: float, eps_position_mm: float, tcp_speed_mm_s: np.ndarray) -> bytes:
    """Smallest singular values of both tasks and the TCP speed against time."""
    fig, axes = _figure(8.0, 5.0, 2, 1, sharex=True)
    top, bottom = axes[0, 0], axes[1, 0]
    top.semilogy(t, np.maximum(sigma_orientation, 1e-12), color=COLOURS[2], label="orientation task (rad/rad)")
    top.axhline(eps_orientation, color=COLOURS[2], linestyle="--", linewidth=0.8, label="its eps")
    top.semilogy(t, np.maximum(sigma_position_mm * 1e-3, 1e-12), color=COLOURS[1], label="position task (m/rad)")
    top.axhline(eps_position_mm * 1e-3, color=COLOURS[1], linestyle="--", linewidth=0.8, label="its eps")
    top.set_ylabel("smallest singular value")
    top.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, frameon=False)
    bottom.plot(t[:-1] if len(tcp_speed_mm_s) == len(t) - 1 else t, tcp_speed_mm_s, color=COLOURS[0])
    bottom.set_ylabel("TCP speed (mm/s)")
    bottom.set_xlabel("t (s)")
    return _png(fig)


def motion_report(title: str, summary: list[str], metrics: dict, series: dict, settings: dict) -> Report:
    """The report of one motion.

    Args:
        summary: paragraphs (inputs, options, verdict).
        metrics: the scalar figures of :func:`torchcal.motion.planner.measure`.
        series: ``t``, ``position_error_mm``, ``orientation_deviation_deg``, ``joint_speed_deg_s``,
            ``joint_accel_deg_s2``, ``singular``, ``sigma_orientation``, ``sigma_position_mm``,
            ``tcp_speed_mm_s`` arrays.
        settings: ``tolerance``, ``orientation_eps``, ``position_eps`` (mm/rad).
    """
    t = series["t"]
    singular = series["singular"]
    n = len(metrics["joint_speed_max_deg_s"])
    rows = [[f"q{j + 1}", f"{metrics['joint_speed_max_deg_s'][j]:.2f}", f"{metrics['joint_speed_limit_deg_s'][j]:.0f}",
             f"{metrics['joint_accel_max_deg_s2'][j]:.1f}", f"{metrics['joint_accel_limit_deg_s2'][j]:.0f}"]
            for j in range(n)]
    figures = [
        ("path_error", "Path error (TCP of each sample against its path point) and orientation deviation",
         path_error_figure(t, series["position_error_mm"], series["orientation_deviation_deg"], singular,
                           settings["tolerance"])),
        ("joint_speed", "Joint speeds by finite differences of the samples, with the limits",
         joint_figure(t[:-1], series["joint_speed_deg_s"], np.array(metrics["joint_speed_limit_deg_s"]),
                      singular[:-1], "joint speed", "deg/s")),
        ("joint_accel", "Joint accelerations by second differences (at rest before and after)",
         joint_figure(t, series["joint_accel_deg_s2"], np.array(metrics["joint_accel_limit_deg_s2"]), singular,
                      "joint acceleration", "deg/s^2")),
        ("singularity", "Smallest singular values of the position and orientation tasks, and the TCP speed",
         singularity_figure(t, series["sigma_orientation"], series["sigma_position_mm"], settings["orientation_eps"],
                            settings["position_eps"], series["tcp_speed_mm_s"])),
    ]
    figure_table = [
        ["path error, max over samples (mm)", f"{metrics['path_error_max_mm']:.3g}"],
        ["path error at start / end (mm)", f"{metrics['start_error_mm']:.3g} / {metrics['end_error_mm']:.3g}"],
        ["path error, max in / outside singular neighbourhoods (mm)",
         f"{metrics['path_error_singular_max_mm']:.3g} / {metrics['path_error_regular_max_mm']:.3g}"],
        ["orientation deviation, max (deg)", f"{metrics['orientation_deviation_max_deg']:.3g}"],
        ["orientation deviation, max in / outside singular neighbourhoods (deg)",
         (f"{metrics['orientation_deviation_singular_max_deg']:.3g} / "
          f"{metrics['orientation_deviation_regular_max_deg']:.3g}")],
        ["samples where the orientation / the position task yields (smallest singular value below its eps)",
         f"{metrics['samples_orientation_yielding']} / {metrics['samples_position_yielding']} of {metrics['n_samples']}"],
        ["duration (s)", f"{metrics['duration_s']:.3f}"],
        ["peak TCP speed (mm/s)", f"{metrics['tcp_speed_max_mm_s']:.1f}"],
    ]
    return Report(title=title, sections=[
        Section("Summary", [Paragraph(p) for p in summary]),
        Section("Figures", [
            Table("motion_figures", ["quantity", "value"], figure_table,
                  caption="Measured on the written samples: forward kinematics of the joints against the path "
                          "point of each sample; nan where a set is empty."),
            Table("joint_limits", ["joint", "peak speed (deg/s)", "limit", "peak acceleration (deg/s^2)", "limit"], rows,
                  caption="Finite differences of the samples every dt."),
        ]),
        Section("Plots", [Figure(name, png, caption) for name, caption, png in figures]),
    ])
