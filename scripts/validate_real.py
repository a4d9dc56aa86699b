"""Reproduce the real-robot validation table: ``python scripts/validate_real.py --data-root ../shared/data/real``.

Reads the public measurements in place (nothing is copied), runs every protocol of
:mod:`torchcal.app.validation` through the fit/evaluate pipeline, and writes ``docs/validation.json``,
the Markdown table (``docs/validation_table.md``, and between the table markers of
``docs/validation.md``) and one error histogram per protocol under ``docs/img/``.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from rich.console import Console

from torchcal.app.validation import PROTOCOLS, STAGES, run_protocol
from torchcal.core.io import atomic_write_bytes, atomic_write_json, atomic_write_text

START, END = "<!-- validation-table:start -->", "<!-- validation-table:end -->"
COVERAGE_START, COVERAGE_END = "<!-- coverage-table:start -->", "<!-- coverage-table:end -->"
#: the method ``torchcal fit`` reports by default (FitConfig.uncertainty)
DEFAULT_METHOD = "conformal"


def _cell(v: float) -> str:
    return f"{v:.3f}" if v >= 0.01 else f"{v:.4f}"


def table(results: list[dict]) -> str:
    """The Markdown table: one block of rows per protocol, one row per stage."""
    lines = [
        "| set | protocol | stage | poses | mean [mm] | RMS [mm] | p95 [mm] | max [mm] | in predicted 95 % | published | note |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        first = True
        for stage, m in r["stages"].items():
            head = (f"{r['dataset']}", r["protocol"]) if first else ("", "")
            published = r["published"] if stage.startswith(STAGES[-1]) else ""  # the sources' results are hybrids
            if "position_mean_mm" not in m:
                lines.append(f"| {head[0]} | {head[1]} | {stage} | | | | | | | {published} | {m['status']} |")
                first = False
                continue
            u = m.get("uncertainty", {}).get(DEFAULT_METHOD)
            inside = f"{u['coverage_95'] * 100:.0f} %" if u else "n/a"
            note = m.get("status", "")
            lines.append(
                f"| {head[0]} | {head[1]} | {stage} | {m['n_poses']} | {_cell(m['position_mean_mm'])} | "
                f"{_cell(m['position_rms_mm'])} | {_cell(m['position_p95_mm'])} | {_cell(m['position_max_mm'])} | "
                f"{inside} | {published} | {note} |"
            )
            first = False
    return "\n".join(lines)


def coverage_table(results: list[dict]) -> str:
    """Per row and method: share of scored points inside their predicted 95 % region, predicted and
    observed 95th percentile of the 3-D error."""
    lines = ["| set | protocol | stage | poses | conformal: inside 95 % | gaussian: inside 95 % | observed p95 [mm] | "
             "conformal: predicted p95 [mm] | gaussian: predicted p95 [mm] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        for stage, m in r["stages"].items():
            u = m.get("uncertainty")
            if not u:
                continue

            def cell(method: str, key: str, u=u) -> str:
                if method not in u:
                    return "n/a"
                v = u[method][key]
                if key == "coverage_95":
                    return f"{100 * v:.1f} %"
                ratio = v / u[method]["observed_p95_mm"] - 1
                return f"{_cell(v)} ({100 * ratio:+.0f} %)"

            lines.append(f"| {r['dataset']} | {r['protocol']} | {stage} | {m['n_poses']} | "
                         f"{cell('conformal', 'coverage_95')} | {cell('gaussian', 'coverage_95')} | "
                         f"{_cell(m['position_p95_mm'])} | {cell('conformal', 'predicted_p95_mm')} | "
                         f"{cell('gaussian', 'predicted_p95_mm')} |")
    return "\n".join(lines)


def _between(body: str, start: str, end: str, text: str) -> str:
    if start not in body or end not in body:
        return body
    head, rest = body.split(start, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{start}\n{text}\n{end}{tail}"


def histogram(result: dict, path: Path) -> None:
    """Histogram of the scored 3-D errors, one outline per stage."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=110)
    per_pose = result["per_pose_mm"]
    top = max(max(v) for v in per_pose.values())
    bins = np.linspace(0.0, top * 1.02, 40)
    for stage, values in per_pose.items():
        mean = float(np.mean(values))
        ax.hist(values, bins=bins, histtype="step", linewidth=1.6, label=f"{stage} (mean {mean:.3f})")
    ax.set_xlabel("3-D position error on poses the fit did not see [mm]" if not result["in_sample"]
                  else "3-D position error, IN-SAMPLE [mm]")
    ax.set_ylabel("poses")
    ax.set_title(f"{result['dataset']}: {result['protocol']}", fontsize=8)
    ax.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data-root", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs"))
    parser.add_argument("--no-residual", action="store_true", help="skip the learned residual stage")
    parser.add_argument("--only", default=None, help="run only this data set")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch intra-op threads (default 1: the fits are many small problems, and on a shared "
                             "2-core machine more threads contend instead of helping)")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(max(1, args.threads))
    root = Path(args.data_root)
    console = Console()
    results = []
    started = time.perf_counter()
    out = Path(args.out)
    for protocol in PROTOCOLS:
        if args.only and protocol.dataset != args.only:
            continue
        with console.status(f"{protocol.dataset}: {protocol.label}"):
            t0 = time.perf_counter()
            result = run_protocol(root, protocol, residual=not args.no_residual)
            result["elapsed_s"] = time.perf_counter() - t0
        histogram(result, out / "img" / f"validation_{result['slug']}.png")
        stages = result["stages"]
        summary = ", ".join(f"{k} {v['position_mean_mm']:.4f}" for k, v in stages.items() if "position_mean_mm" in v)
        console.log(f"{protocol.dataset} / {protocol.label} ({result['elapsed_s']:.0f} s): mean [mm] {summary}")
        results.append(result)
    total = time.perf_counter() - started
    text = table(results)
    footer = f"\n\nRegenerated in {total:.0f} s on {os.cpu_count()} CPU core(s) by `scripts/validate_real.py`.\n"
    atomic_write_json(out / "validation.json", {"results": results, "elapsed_s": total})
    coverage = coverage_table(results)
    atomic_write_text(out / "validation_table.md", text + footer + "\n" + coverage + "\n")
    page = out / "validation.md"
    if page.is_file() and not args.only:
        body = _between(page.read_text(), START, END, text + footer.rstrip("\n"))
        atomic_write_text(page, _between(body, COVERAGE_START, COVERAGE_END, coverage))
    console.print(text)
    console.print(coverage)
    console.print(footer)


if __name__ == "__main__":
    main()
