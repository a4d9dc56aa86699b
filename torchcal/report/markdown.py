"""The calibration report as one Markdown page next to its PNG figures."""

from __future__ import annotations

from pathlib import Path

from torchcal.core.io import atomic_write_text


def metrics_table(rows: dict[str, dict[str, float]]) -> str:
    head = "| stage | poses | RMS [mm] | mean [mm] | p95 [mm] | max [mm] | AP [mm] |\n|---|---|---|---|---|---|---|"
    lines = [head]
    for stage, m in rows.items():
        lines.append(
            f"| {stage} | {m['n_poses']} | {m['position_rms_mm']:.4f} | {m['position_mean_mm']:.4f} | "
            f"{m['position_p95_mm']:.4f} | {m['position_max_mm']:.4f} | {m['iso9283_AP_mm']:.4f} |"
        )
    return "\n".join(lines)


def parameter_table(parameters: dict[str, dict], truth: dict[str, float] | None = None) -> str:
    head = "| parameter | value | sigma | estimated |" + (" truth | (est-truth)/sigma |" if truth else "")
    sep = "|---|---|---|---|" + ("---|---|" if truth else "")
    lines = [head, sep]
    for name, p in parameters.items():
        unit = "deg" if name.rstrip("0123456789").endswith(("alpha", "beta", "theta", "rx", "ry", "rz")) else "mm"
        row = f"| {name} | {p['value']:.5f} {unit} | {p['sigma']:.5f} | {'yes' if p['estimated'] else 'fixed'} |"
        if truth:
            t = truth.get(name)
            if t is None or not p["estimated"] or p["sigma"] <= 0:
                row += " | |"
            else:
                row += f" {t:.5f} | {(p['value'] - t) / p['sigma']:+.2f} |"
        lines.append(row)
    return "\n".join(lines)


def write_report(path: str | Path, sections: list[tuple[str, str]], title: str) -> Path:
    body = [f"# {title}", ""]
    for heading, text in sections:
        body += [f"## {heading}", "", text.strip(), ""]
    atomic_write_text(path, "\n".join(body))
    return Path(path)
