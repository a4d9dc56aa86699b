"""Benchmark: wall time of ``torchcal fit`` on 3000 UR10 poses, the default against its parts.

The default fit (grouped 5-fold cross-validation of six joint-space structures and two residual
heads, then the chosen model on all poses) against geometry alone (``residual=none
gravity_compliance=none joint_harmonics=none``) and the structure selection without heads
(``residual=none``), on the same 3000 rows of ipa-ur10-tmac series A (numpy ``default_rng(0)``
permutation, file order), each through the command line in a fresh process. Median of repeats;
results in docs/bench_fit.json and docs/bench_fit.md.

    python scripts/bench_fit.py --data-root ../shared/data/real [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from torchcal.core.io import atomic_write_json, atomic_write_text

CASES = {
    "geometry alone": ["residual=none", "gravity_compliance=none", "joint_harmonics=none"],
    "structure selection, no heads": ["residual=none"],
    "default fit": [],
}


def _subset(root: Path, folder: Path) -> Path:
    lines = (root / "ipa-ur10-tmac" / "poses_A_grid.csv").read_text().splitlines()
    rows = np.sort(np.random.default_rng(0).permutation(len(lines) - 1)[:3000]) + 1
    path = folder / "A3000.csv"
    path.write_text("\n".join([lines[0]] + [lines[i] for i in rows]) + "\n")
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data-root", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs"))
    args = parser.parse_args()
    root = Path(args.data_root)
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        data = _subset(root, Path(tmp))
        robot = root / "ipa-ur10-tmac" / "robot.yaml"
        for name, options in CASES.items():
            times = []
            for k in range(args.repeats):
                cmd = [sys.executable, "-m", "torchcal.cli", "fit", "--robot", str(robot), "--data", str(data),
                       "--out", str(Path(tmp) / f"m{k}"), "progress=false", *options]
                started = time.perf_counter()
                subprocess.run(cmd, check=True, capture_output=True)
                times.append(time.perf_counter() - started)
                print(f"{name}: {times[-1]:.1f} s", flush=True)
            results[name] = {"median_s": statistics.median(times), "runs_s": times, "options": options}
    meta = {"poses": 3000, "data": "ipa-ur10-tmac series A, default_rng(0) rows", "repeats": args.repeats,
            "cpu_count": os.cpu_count(), "machine": platform.machine(), "load_average": os.getloadavg()}
    atomic_write_json(Path(args.out) / "bench_fit.json", {"meta": meta, "results": results})
    lines = ["# `torchcal fit` on 3000 UR10 poses", "",
             f"Median of {args.repeats} runs, each a fresh `torchcal fit` process (import time included), "
             f"{meta['cpu_count']} cores, load average at the end {meta['load_average'][0]:.1f}.", "",
             "| case | options | median [s] | runs [s] |", "|---|---|---:|---|"]
    for name, r in results.items():
        lines.append(f"| {name} | `{' '.join(r['options']) or '(none)'}` | {r['median_s']:.1f} | "
                     + ", ".join(f"{t:.1f}" for t in r["runs_s"]) + " |")
    atomic_write_text(Path(args.out) / "bench_fit.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
