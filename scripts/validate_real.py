"""Reproduce the real-robot validation table: ``python scripts/validate_real.py --data-root ../shared/data/real``.

Reads the public measurements in place (nothing is copied), runs every protocol of
:mod:`torchcal.validation`, and writes ``docs/validation.json``, ``docs/validation.md`` (table)
and per-set error histograms under ``docs/img/``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from rich.console import Console

from torchcal.io import atomic_write_json, atomic_write_text
from torchcal.validation import PROTOCOLS, run_protocol


def _table(results: list[dict]) -> str:
    lines = [
        "| set | protocol | stage | poses | mean [mm] | RMS [mm] | p95 [mm] | max [mm] | in 95 % ellipsoid | published |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        for stage, m in r["stages"].items():
            inside = f"{m['inside_95_fraction'] * 100:.0f} %" if "inside_95_fraction" in m else ""
            lines.append(
                f"| {r['dataset']} | {r['protocol']} | {stage} | {m['n_poses']} | {m['position_mean_mm']:.4f} | "
                f"{m['position_rms_mm']:.4f} | {m['position_p95_mm']:.4f} | {m['position_max_mm']:.4f} | {inside} | "
                f"{r['published'] if stage == 'geometric' else ''} |"
            )
        for note in sorted(set(r.get("residual_decisions", []))):
            lines.append(f"| | | residual gate | | | | | | | {note} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data-root", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs"))
    parser.add_argument("--no-residual", action="store_true", help="geometric stages only")
    parser.add_argument("--only", default=None, help="run only this data set")
    args = parser.parse_args()
    root = Path(args.data_root)
    console = Console()
    results = []
    started = time.perf_counter()
    for protocol in PROTOCOLS:
        if args.only and protocol.dataset != args.only:
            continue
        with console.status(f"{protocol.dataset}: {protocol.label}"):
            t0 = time.perf_counter()
            result = run_protocol(root, protocol, residual=not args.no_residual)
            result["elapsed_s"] = time.perf_counter() - t0
        geo = result["stages"]["geometric"]
        console.log(f"{protocol.dataset} / {protocol.label}: geometric mean {geo['position_mean_mm']:.4f} mm, RMS {geo['position_rms_mm']:.4f} mm")
        results.append(result)
    total = time.perf_counter() - started
    out = Path(args.out)
    atomic_write_json(out / "validation.json", {"results": results, "elapsed_s": total})
    atomic_write_text(out / "validation_table.md", _table(results) + f"\n\nRegenerated in {total:.0f} s.\n")
    console.print(_table(results))


if __name__ == "__main__":
    main()
