"""The report of a fit or an evaluation that has no pose-level report of its own (tracer, stiffness, sensor...).

It holds what every instrument has: the lines the command printed (the before/after figures), its
metrics, and, for a folder with a robot geometry, the instrument frame and tool, the parameters
against nominal with 1-sigma and their correlations (:func:`~torchcal.report.parameters.parameter_sections`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from torchcal.core.errors import TorchcalError
from torchcal.report.document import Paragraph, Preformatted, Report, Section, Table
from torchcal.report.parameters import parameter_sections
from torchcal.stages.store import load_model


def _flatten(value, prefix: str = "") -> list[list[str]]:
    """``[key, value]`` rows of a JSON-like document: nested keys dotted, short number lists inline."""
    if isinstance(value, dict):
        return [row for k, v in value.items() for row in _flatten(v, f"{prefix}.{k}" if prefix else str(k))]
    if isinstance(value, bool) or value is None:
        return [[prefix, str(value)]]
    if isinstance(value, (int, float)):
        return [[prefix, f"{value:.6g}" if isinstance(value, float) and math.isfinite(value) else str(value)]]
    if isinstance(value, list):
        if len(value) <= 9 and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            return [[prefix, ", ".join(f"{v:.6g}" for v in value)]]
        if all(isinstance(v, list) for v in value) and len(value) <= 4:
            return [[f"{prefix}[{i}]", row[1]] for i, v in enumerate(value) for row in _flatten(v, "")]
        return [[prefix, f"({len(value)} values)"]]
    text = str(value)
    return [[prefix, text if len(text) <= 200 else text[:197] + "..."]]


def summary_report(title: str, lines: list[str], *, metrics: dict | None = None, folder: Path | None = None,
                   kind: str = "") -> Report:
    """A report of ``lines`` (what the command printed), ``metrics`` and the model ``folder``'s parameters."""
    sections = [Section("Results", [
        Paragraph(f"This report of a {kind or 'measurement'} file holds what the command printed, its metrics and the "
                  "parameters of the model folder; the per-pose, per-axis, per-joint and workspace analyses are made "
                  "for tracker files (x, y, z points)."),
        Preformatted("\n".join(lines) or "(no lines)")])]
    if metrics:
        sections.append(Section("Metrics", [Table("metrics", ["metric", "value"], _flatten(metrics))]))
    if folder is not None and (Path(folder) / "calibration.json").is_file():
        try:
            stored = load_model(folder)
        except TorchcalError as exc:
            sections.append(Section("Parameters", [Paragraph(f"The model folder's parameters could not be read: {exc}")]))
        else:
            fit_metrics = stored.metadata.get("fit_metrics")
            if fit_metrics and not metrics:
                sections.append(Section("Metrics of the fit", [Table("fit_metrics", ["metric", "value"], _flatten(fit_metrics))]))
            for stage in stored.stages():  # a stage's own table (the stiffness: its springs)
                table = stage.report_table()
                if table is not None:
                    sections.append(Section(table.title, [Table(stage.name, table.columns, table.rows)]))
            sections += parameter_sections(stored)
            notes = stored.metadata.get("notes")
            if notes:
                sections.append(Section("Notes and warnings", [Preformatted("\n".join(str(n) for n in notes))]))
    elif folder is not None and (Path(folder) / "sensor.json").is_file():
        doc = json.loads((Path(folder) / "sensor.json").read_text(encoding="utf-8"))
        sections.append(Section("Sensor mounting", [Table("sensor", ["entry", "value"], _flatten(doc))]))
    return Report(title, sections)
