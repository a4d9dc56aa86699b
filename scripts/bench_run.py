"""Wall and CPU time of `torchcal run` (the default twin, with its export and report), this tree
against a baseline source tree, interleaved, each a fresh process; and whether the two write the
same results.

    .venv/bin/python scripts/bench_run.py --base /tmp/base37 --repeats 3

The baseline is another checkout of torchcal (e.g. ``git worktree add --detach /tmp/base37 <commit>``),
run by the same interpreter with ``PYTHONPATH`` pointing at it. Each repeat runs the baseline, then
this tree; the 1-minute load average before each run is recorded beside it (the machine may be
shared). CPU seconds are user + system of the child process (all its threads) and of the worker
processes it started and ended (:mod:`torchcal.core.workers`). With ``--serial``, this tree also runs
with ``fit.jobs=1`` (everything in one process) in each repeat.

Same results (the same text; for a JSON file, else the largest relative difference of its numbers,
at most 1e-9 to pass): ``metrics.json`` (less ``elapsed_s``), ``model/calibration.json``,
``model/metrics.json``, ``model/model_selection.json``, ``model/uncertainty.json``, ``report.md``
and the export's ``manifest.json`` (less its hashes and versions, which name the files' bytes and the build),
the output folders' names replaced.

Writes ``docs/bench_run.json`` and ``docs/bench_run.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NAME = "twin-default"
COMPARED = ["metrics.json", "model/calibration.json", "model/metrics.json", "model/model_selection.json",
            "model/uncertainty.json", "report.md"]


def run_once(tree: Path, out: Path, export: Path, extra: tuple[str, ...] = ()) -> dict:
    """One fresh `torchcal run` of the source tree ``tree`` (``extra``: overrides): wall and CPU seconds
    (the process and its worker processes), load before."""
    for folder in (out, export):
        shutil.rmtree(folder, ignore_errors=True)
    env = {**os.environ, "PYTHONPATH": str(tree)}
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    # as the `torchcal` command runs it (console_main), or main() in trees older than it
    code = ("import sys; from torchcal import cli; sys.argv[0] = 'torchcal'; "
            "cli.console_main() if hasattr(cli, 'console_main') else sys.exit(cli.main())")
    proc = subprocess.run([sys.executable, "-c", code, "run", f"out={out}", f"export_dir={export}", *extra],
                          env=env, cwd=tree, capture_output=True, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"torchcal run failed in {tree} (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": wall, "cpu_s": cpu, "load_1min_before": load}


def _normalized(path: Path, folders: list[Path]) -> str:
    text = path.read_text(encoding="utf-8")
    for k, folder in enumerate(folders):
        text = text.replace(str(folder), f"<folder{k}>")
    if path.name == "metrics.json" and path.parent.name == NAME:
        data = json.loads(text)
        data.pop("elapsed_s", None)
        text = json.dumps(data, indent=1, sort_keys=True)
    if path.name == "manifest.json":
        data = json.loads(text)
        for key in ("files", "versions", "sha256", "created"):
            data.pop(key, None)
        text = json.dumps(data, indent=1, sort_keys=True)
    return text


#: Numbers of a JSON file that differ by at most this (relative) count as the same result.
SAME_RELATIVE = 1e-9


def _largest_difference(a, b) -> float | None:
    """Largest relative difference between the numbers of two parsed JSON documents of the same shape
    (``None``: not the same shape, or a text or flag differs)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return None
        parts = [_largest_difference(a[k], b[k]) for k in a]
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return None
        parts = [_largest_difference(x, y) for x, y in zip(a, b)]
    elif isinstance(a, bool) or isinstance(b, bool) or not isinstance(a, int | float) or not isinstance(b, int | float):
        return 0.0 if a == b else None
    elif a == b or (a != a and b != b):  # equal, or both NaN
        return 0.0
    else:
        return abs(a - b) / max(abs(a), abs(b))
    return None if any(p is None for p in parts) else max(parts, default=0.0)


def same_results(a: tuple[Path, Path], b: tuple[Path, Path]) -> dict[str, float | None]:
    """How far each compared file of the runs ``a`` and ``b`` (each ``(out, export)``) is from the other's:
    0 for the same text, the largest relative difference of its numbers for a JSON file of the same
    shape, ``None`` otherwise (a file missing, a text or a shape that differs)."""
    result: dict[str, float | None] = {}
    pairs = [(name, a[0] / NAME / name, b[0] / NAME / name) for name in COMPARED]
    pairs.append(("export manifest.json", a[1] / NAME / "manifest.json", b[1] / NAME / "manifest.json"))
    for name, pa, pb in pairs:
        if not pa.is_file() and not pb.is_file():
            continue
        if not (pa.is_file() and pb.is_file()):
            result[name] = None
            continue
        ta, tb = _normalized(pa, [a[0], a[1]]), _normalized(pb, [b[0], b[1]])
        if ta == tb:
            result[name] = 0.0
        elif pa.suffix == ".json":
            result[name] = _largest_difference(json.loads(ta), json.loads(tb))
        else:
            result[name] = None
    return result


def _combined(x: float | None, y: float | None) -> float | None:
    return None if x is None or y is None else max(x, y)


def _said(difference: float | None) -> str:
    if difference is None:
        return "NO"
    return "yes" if difference == 0 else f"numbers within {difference:.0e} relative"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", type=Path, required=True, help="baseline source tree (a torchcal checkout)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "bench_run")
    parser.add_argument("--serial", action="store_true",
                        help="also run this tree with fit.jobs=1 (everything in one process), interleaved")
    args = parser.parse_args()
    trees = {"baseline": args.base.resolve(), "this tree": ROOT}
    if args.serial:
        trees["this tree, fit.jobs=1"] = ROOT
    work = Path(tempfile.mkdtemp(prefix="bench_run_"))
    runs: dict[str, list[dict]] = {k: [] for k in trees}
    same: dict[str, float | None] = {}
    for r in range(args.repeats):
        for label, tree in trees.items():
            tag = {"baseline": "base", "this tree": "new"}.get(label, "serial")
            out, export = work / f"{tag}_out", work / f"{tag}_export"
            extra = ("fit.jobs=1",) if tag == "serial" else ()
            runs[label].append(run_once(tree, out, export, extra))
            print(f"repeat {r + 1} {label}: {runs[label][-1]}", flush=True)
        checked = same_results((work / "base_out", work / "base_export"), (work / "new_out", work / "new_export"))
        if args.serial:  # the serial run of this tree must write what the baseline wrote too
            serial = same_results((work / "base_out", work / "base_export"), (work / "serial_out", work / "serial_export"))
            checked = {k: _combined(v, serial.get(k)) for k, v in checked.items()}
        same = checked if not same else {k: _combined(same[k], v) for k, v in checked.items()}
    shutil.rmtree(work, ignore_errors=True)
    summary = {label: {"median_wall_s": statistics.median(x["wall_s"] for x in rs),
                       "median_cpu_s": statistics.median(x["cpu_s"] for x in rs), "runs": rs}
               for label, rs in runs.items()}
    record = {"command": "torchcal run (default twin, export and report)", "baseline": str(args.base),
              "cores": os.cpu_count(), "repeats": args.repeats, "results": summary, "same_results": same}
    args.out.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    lines = ["| tree | median wall [s] | median CPU [s] | runs: wall / CPU [s] (1-min load before) |", "|---|---:|---:|---|"]
    for label, s in summary.items():
        each = "; ".join(f"{x['wall_s']:.1f} / {x['cpu_s']:.1f} ({x['load_1min_before']:.2f})" for x in s["runs"])
        lines.append(f"| {label} | {s['median_wall_s']:.1f} | {s['median_cpu_s']:.1f} | {each} |")
    lines.append("")
    lines.append("Same results as the baseline: " + ", ".join(f"{k} {_said(v)}" for k, v in same.items()) + ".")
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    print("\n".join(lines))
    return 0 if all(v is not None and v <= SAME_RELATIVE for v in same.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
