"""``torchcal run`` of this tree against another revision, back to back: ``python scripts/bench_run_joint_models.py --base main``.

The other revision is extracted with ``git archive`` into a temporary folder and run with this
environment's interpreter (its package and ``configs/`` first on the path). Each repeat runs both,
alternating which goes first; the median wall time of each is written to
``docs/bench_run_joint_models.md`` with the held-out RMS each printed.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from torchcal.core.io import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _run(tree: Path, out: Path, name: str) -> tuple[float, float, float]:
    """Wall seconds of one ``torchcal run`` from ``tree``, its CPU seconds (user + system: less
    sensitive to other load on a shared machine) and the held-out RMS it reports (mm)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    # as the `torchcal` command runs it (console_main), or main() in trees older than it
    code = ("import sys; from torchcal import cli; sys.argv[0] = 'torchcal'; "
            "cli.console_main() if hasattr(cli, 'console_main') else sys.exit(cli.main())")
    start, cpu = time.perf_counter(), _cpu()
    subprocess.run([sys.executable, "-c", code, "run", f"out={out}", f"export_dir={out / 'exported'}", f"name={name}",
                    "fit.progress=false"], cwd=tree, env=env, check=True, capture_output=True)
    seconds, cpu = time.perf_counter() - start, _cpu() - cpu
    metrics = json.loads((out / name / "metrics.json").read_text(encoding="utf-8"))
    return seconds, cpu, float(metrics["test"][metrics["final_stage"]]["position_rms_mm"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--base", default="main", help="git revision to compare against")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="docs/bench_run_joint_models.md")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "base"
        base.mkdir()
        archive = subprocess.run(["git", "archive", args.base], cwd=ROOT, check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(base)], input=archive, check=True)
        times: dict[str, list[float]] = {"base": [], "this": []}
        cpus: dict[str, list[float]] = {"base": [], "this": []}
        rms: dict[str, float] = {}
        for r in range(args.repeats):
            order = [("base", base), ("this", ROOT)] if r % 2 == 0 else [("this", ROOT), ("base", base)]
            for label, tree in order:
                seconds, cpu, rms[label] = _run(tree, Path(tmp) / "runs", f"{label}{r}")
                times[label].append(seconds)
                cpus[label].append(cpu)
                print(label, f"{seconds:.1f} s", f"cpu {cpu:.1f} s", f"{rms[label]:.4f} mm", flush=True)
    med = {k: statistics.median(v) for k, v in times.items()}
    med_cpu = {k: statistics.median(v) for k, v in cpus.items()}
    lines = [f"# `torchcal run`: this tree against `{args.base}`",
             "",
             f"`python scripts/bench_run_joint_models.py --base {args.base}`: {args.repeats} repeats back to back, "
             "alternating which runs first; wall seconds of the whole command (twin, fit, CV, report, export).",
             "",
             "| tree | wall [s] | median wall [s] | CPU [s] | median CPU [s] | held-out RMS [mm] |",
             "|---|---|---|---|---|---|"]
    for label in ("base", "this"):
        lines.append(f"| {args.base if label == 'base' else 'this tree'} | {', '.join(f'{t:.1f}' for t in times[label])} | "
                     f"{med[label]:.1f} | {', '.join(f'{t:.1f}' for t in cpus[label])} | {med_cpu[label]:.1f} | "
                     f"{rms[label]:.4f} |")
    lines += ["", f"Ratio of medians: wall {med['this'] / med['base']:.2f}, CPU {med_cpu['this'] / med_cpu['base']:.2f}."]
    atomic_write_text(ROOT / args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
