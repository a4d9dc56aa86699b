"""The frames and parameter sections of every report of a geometry model folder.

:func:`parameter_sections` is shared by the tracker's calibration report and the generic report of
every other instrument: the instrument frame and tool, the parameters against nominal with 1-sigma
(mm, deg), their correlations and the prior's sections.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchcal.report import plots
from torchcal.report.document import Paragraph, PendingFigure, Section, Table
from torchcal.report.prior import prior_sections
from torchcal.stages.store import StoredModel, frame_entries

#: Parameter pairs whose correlation exceeds this are listed under the heatmap.
STRONG_CORRELATION = 0.9


def _g(value: float) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.3g}"


def frames_table(stored: StoredModel) -> Table:
    """The instrument-to-base transform and the tool, mm and deg with 1-sigma."""
    frames = frame_entries(stored.model, stored.x, stored.free, stored.covariance)
    rows = []
    for key, what in (("T_instrument_base", "robot base in the instrument frame"), ("T_flange_tool", "tool (TCP) in the flange frame")):
        f = frames[key]
        rows.append([f"{key}: {what}"] + [f"{f[a]:.4f} ± {f['sigma'][a]:.4f}" for a in ("x", "y", "z")]
                    + [f"{f[a]:.5f} ± {f['sigma'][a]:.5f}" for a in ("rx", "ry", "rz")])
    return Table("frames", ["transform", "x [mm]", "y [mm]", "z [mm]", "rx [deg]", "ry [deg]", "rz [deg]"], rows,
                 caption=frames["convention"] + ".")


def parameter_sections(stored: StoredModel, truth_x: torch.Tensor | None = None, truth_note: str = "") -> list[Section]:
    """Frames, parameters against nominal with 1-sigma, and their correlations (every geometry model folder)."""
    layout = stored.model.layout
    scale = layout.unit_scale()
    angle = layout.is_angle()
    nominal = stored.model.nominal_vector().cpu()
    x = stored.x.detach().cpu()
    free = stored.free.tolist()
    sigma = stored.covariance.diagonal().clamp_min(0).sqrt().cpu()
    sigma_of = {i: float(sigma[k]) for k, i in enumerate(free)}
    dropped = (stored.metadata.get("identifiability") or {}).get("not_identifiable") or {}
    rows = []
    unused: list[str] = []
    tool_rotation = range(layout.tool_slice.start + 3, layout.tool_slice.stop)
    for i, name in enumerate(layout.names):
        if layout.base_slice.start <= i < layout.base_slice.stop or (i in tool_rotation and i not in sigma_of):
            continue  # the frame is a transform, not a robot parameter: in the table above
        unit = "deg" if bool(angle[i]) else "mm"
        s = float(scale[i])
        value, nom = float(x[i]) * s, float(nominal[i]) * s
        change = value - nom
        if i in sigma_of:
            sg = sigma_of[i] * s
            status = "estimated"
            ratio = f"{abs(change) / sg:.1f}" if sg > 0 else "-"
            sg_text = _g(sg)
        elif name in dropped:
            status = f"not identifiable (with {', '.join(dropped[name][:2]) or 'nothing: no effect on the TCP'})"
            sg_text, ratio = "-", "-"
        else:
            if change == 0.0:
                unused.append(name)
                continue
            status, sg_text, ratio = "fixed by the model structure", "-", "-"
        row = [name, unit, f"{nom:.5f}", f"{value:.5f}", f"{change:+.5f}", sg_text, ratio, status]
        if truth_x is not None:
            if i in sigma_of and sigma_of[i] > 0:
                t = float(truth_x[i]) * s
                row += [f"{t:.5f}", f"{(value - t) / (sigma_of[i] * s):+.2f}"]
            else:
                row += ["", ""]
        rows.append(row)
    columns = ["parameter", "unit", "nominal", "calibrated", "change", "1-sigma", "|change|/sigma", "status"]
    if truth_x is not None:
        columns += ["truth (projected)", "(calibrated - truth)/sigma"]
    blocks: list = [
        Paragraph("MDH parameters (alpha = alpha_(i-1), a = a_(i-1), beta = Hayati tilt of nearly parallel axes, theta = "
                  "joint zero offset, d = d_i) and the tool point, against the nominal robot file. 1-sigma from the "
                  "covariance of the fit (residual variance times (J^T J)^-1), widened to the cluster-robust estimate "
                  "over the cross-validation's configuration regions where that is larger (residuals correlated "
                  "within a region). It describes the scatter of the estimate, not a bias from physics the model "
                  "lacks: a parameter that absorbs such an error can sit several sigma from the physical value. "
                  "|change|/sigma below about 3 is a change the data cannot distinguish from none." + (
                      f" Not listed: {', '.join(unused)}, fixed at nominal by the model structure (beta only on "
                      "nearly parallel axes, where d is fixed instead)." if unused else "") + (
                      f" {truth_note}" if truth_note else "")),
        Table("parameters", columns, rows),
    ]
    cov = stored.covariance.detach().cpu().to(torch.float64).numpy()
    names = stored.free_names
    if len(names) > 1:
        d = np.sqrt(np.clip(np.diag(cov), 0, None))
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = np.where(np.outer(d, d) > 0, cov / np.outer(d, d), 0.0)
        np.fill_diagonal(corr, 1.0)
        pairs = [(abs(corr[a, b]), names[a], names[b], corr[a, b]) for a in range(len(names)) for b in range(a + 1, len(names))
                 if abs(corr[a, b]) > STRONG_CORRELATION]
        pairs.sort(reverse=True)
        blocks.append(PendingFigure("correlation", plots.correlation_heatmap, (corr, names),
                             "Correlation matrix of the identified parameters (from the fit's covariance)."))
        if pairs:
            blocks.append(Table("correlations", ["parameter", "parameter", "correlation"],
                                [[a, b, f"{c:+.3f}"] for _, a, b, c in pairs[:20]],
                                caption=f"Pairs correlated beyond ±{STRONG_CORRELATION:g} (at most 20, strongest first): "
                                        "the data barely separate them, so their sigmas are large and their values trade "
                                        "off against each other."))
        else:
            blocks.append(Paragraph(f"No two identified parameters are correlated beyond ±{STRONG_CORRELATION:g}."))
    return [
        Section("Instrument frame and tool", [Paragraph(
            "Where the robot stands in the instrument's frame and where the measured point sits on the flange, as "
            "identified (calibration.json frames holds the same, with the 4x4 matrix)."), frames_table(stored)]),
        Section("Parameters against nominal", blocks),
        *prior_sections(stored.metadata),
    ]
