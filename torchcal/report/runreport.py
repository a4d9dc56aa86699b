"""The report of a run: metrics table, parameters with sigmas, identifiability, figures."""

from __future__ import annotations

from pathlib import Path

import torch

from torchcal.identify.calibrate import CalibrationResult
from torchcal.kinematics.robot import RobotModel
from torchcal.report import plots
from torchcal.report.markdown import metrics_table, write_report


def write_run_report(folder: Path, robot: RobotModel, result: CalibrationResult, stages: dict[str, torch.Tensor],
                     summary: dict, truth_x: torch.Tensor | None = None) -> Path:
    """Write ``report.md`` with figures into ``folder``; returns the report path."""
    folder = Path(folder)
    figs = folder / "figures"
    errors_mm = {k: (v.norm(dim=-1) * 1e3).numpy() for k, v in stages.items()}
    plots.error_histogram(errors_mm, figs / "error_histogram.png", "held-out 3-D position error")
    plots.per_pose_errors(errors_mm, figs / "per_pose_error.png", "held-out 3-D position error per pose")
    plots.convergence(result.solve.history, figs / "convergence.png")
    scale = result.model.layout.unit_scale()
    sigma = result.parameter_sigma()
    lines = ["| parameter | estimate | sigma | truth (projected) | z |", "|---|---|---|---|---|"]
    for k, (idx, name) in enumerate(zip(result.free.tolist(), result.free_names)):
        unit = "deg" if bool(result.model.layout.is_angle()[idx]) else "mm"
        est = float(result.x[idx] * scale[idx])
        sg = float(sigma[k] * scale[idx])
        if truth_x is not None:
            tr = float(truth_x[idx] * scale[idx])
            lines.append(f"| {name} | {est:.5f} {unit} | {sg:.5f} | {tr:.5f} | {(est - tr) / sg:+.2f} |")
        else:
            lines.append(f"| {name} | {est:.5f} {unit} | {sg:.5f} | | |")
    floor = summary.get("noise_floor_rms_mm")
    honest = []
    geo = summary["test"]["geometric"]["position_rms_mm"]
    structure = summary.get("model", "geometry").split(" + mlp")[0].split(" + mma-elm")[0]
    if floor:
        ratio = geo / floor
        if ratio > 1.2:
            honest.append(
                f"The calibrated model ({structure}) leaves {geo:.4f} mm RMS on held-out poses, {ratio:.1f}x the "
                f"measurement noise floor ({floor:.4f} mm): the rest is what this model cannot express."
            )
        else:
            honest.append(f"The calibrated model ({structure}) reaches {geo:.4f} mm RMS, {ratio:.2f}x the noise floor "
                          f"{floor:.4f} mm: nothing systematic is left.")
    if summary.get("residual"):
        honest.append(str(summary["residual"].get("decision", "")))
    tc = summary.get("truth_check")
    truth_text = ""
    if tc:
        truth_text = (
            f"{tc['fraction_within_3_sigma'] * 100:.1f} % of the {tc['identifiable_parameters']} identified parameters lie within "
            f"3 sigma of the twin's truth (projected onto the identified set; projection residual "
            f"{tc['projection_residual_rms_mm']:.2e} mm)."
        )
    selection = summary.get("residual") or {}
    table = selection.get("table")
    sections = [
        ("Model selection (grouped cross-validation on the training poses)",
         f"```\n{table}\n```" if table else "No choice to make: every structure option was set explicitly."),
        ("Accuracy on held-out poses", metrics_table(summary["test"]) + "\n\n![histogram](figures/error_histogram.png)\n\n![per pose](figures/per_pose_error.png)"),
        ("What is left", "\n\n".join(honest)),
        ("Identifiability", "```\n" + result.identifiability.summary() + "\n```"),
        ("Parameters (1 sigma from the residual variance)", (truth_text + "\n\n" if truth_text else "") + "\n".join(lines)),
        ("Convergence", f"{result.method}: {result.solve.iterations} iterations, {result.solve.message}.\n\n![convergence](figures/convergence.png)"),
    ]
    path = write_report(folder / "report.md", sections, f"torchcal report: {robot.name} ({summary['name']})")
    return path
