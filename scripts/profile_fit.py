"""Profile: where the default fit's time goes, by stage, on the twin and two real sets.

Cases (each a fresh process running the command in-process, so stage timers can wrap the
library functions): ``torchcal run`` (the default twin: fit, held-out evaluation, export,
report); ``torchcal fit`` on 3000 seeded rows of ipa-ur10-tmac series A (numpy
``default_rng(0)`` permutation, file order: the rows of ``scripts/bench_fit.py``); ``torchcal fit``
on the 1000 poses of jacobi-ur5-gts3800. Stages are exclusive (a stage's time excludes the
stages nested in it): folds, structure CV (configuration regions; again on blocks of
measurement order when a kept head is checked there), final structure fit, uncertainty
calibration, model folder, head CV, kept head fit, held-out evaluation, export, report and
plots, and the rest (loading, import, console). Wall and CPU seconds (all threads of this
process: the work of the fit's worker processes, torchcal.core.workers, shows in a stage's wall
time only, and in the total CPU of ``scripts/bench_run.py``) per stage;
the machine's load average next to each run. Median of ``--repeats`` per case; with
``--baseline DIR`` the same cases also run on the source tree ``DIR`` (imported instead of the installed one),
interleaved run by run so that machine load affects both alike. Results in
docs/profile_fit.json and docs/profile_fit.md.

    python scripts/profile_fit.py --data-root ../shared/data/real [--repeats 3] [--baseline /tmp/base]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: (module, function, stage): the library functions each stage's timer wraps.
STAGES = [
    ("torchcal.stages.geometry", "make_config_folds", "folds"),
    ("torchcal.stages.geometry", "cross_validate_structures", "structure CV"),
    ("torchcal.stages.residual", "cross_validate_structures", "structure CV"),
    ("torchcal.stages.geometry", "fit_with_selection", "final structure fit"),
    ("torchcal.stages.pipeline", "fit_with_selection", "final structure fit"),
    ("torchcal.stages.geometry", "calibrate_errors", "uncertainty calibration"),
    ("torchcal.stages.residual", "calibrate_errors", "uncertainty calibration"),
    ("torchcal.stages.geometry", "point_jacobian", "uncertainty calibration"),
    ("torchcal.stages.residual", "point_jacobian", "uncertainty calibration"),
    ("torchcal.stages.pipeline", "save_fit", "model folder"),
    ("torchcal.stages.residual", "cross_validate_heads", "head CV"),
    ("torchcal.stages.residual", "fit_before_gate", "kept head fit"),
    ("torchcal.instruments.tracker.run", "held_out_errors", "held-out evaluation"),
    ("torchcal.instruments.tracker.run", "nominal_errors", "held-out evaluation"),
    ("torchcal.instruments.tracker.run", "export_and_check", "export"),
    ("torchcal.instruments.tracker.run", "_write_report", "report and plots"),
    ("torchcal.instruments.tracker.report", "calibration_report", "report and plots"),
    ("torchcal.report.document", "write_report", "report and plots"),
]


def _child(case: str, data_root: str, out: str) -> None:
    """Run one case in this process with stage timers; print one JSON line of stage times."""
    import importlib

    tree = os.environ.get("TORCHCAL_TREE")
    if tree:  # the baseline's source tree instead of the installed (editable) torchcal
        sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f)]
        sys.path.insert(0, tree)
    wall: dict[str, float] = {}
    cpu: dict[str, float] = {}
    stack: list[list[float]] = []  # per open stage: [child wall, child cpu]

    def timed(fn, stage):
        def wrapper(*args, **kwargs):
            stack.append([0.0, 0.0])
            w0, c0 = time.perf_counter(), time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                dw, dc = time.perf_counter() - w0, time.process_time() - c0
                inner_w, inner_c = stack.pop()
                wall[stage] = wall.get(stage, 0.0) + dw - inner_w
                cpu[stage] = cpu.get(stage, 0.0) + dc - inner_c
                if stack:
                    stack[-1][0] += dw
                    stack[-1][1] += dc
        return wrapper

    w0, c0 = time.perf_counter(), time.process_time()
    for module, name, stage in STAGES:
        try:
            mod = importlib.import_module(module)
        except ImportError:
            continue
        if hasattr(mod, name):
            setattr(mod, name, timed(getattr(mod, name), stage))
    from torchcal.cli import main

    root = Path(data_root)
    if case == "twin":
        argv = ["run", f"out={out}", f"export_dir={out}/exported"]
    elif case.startswith("ur10-A3000"):
        lines = (root / "ipa-ur10-tmac" / "poses_A_grid.csv").read_text().splitlines()
        rows = np.sort(np.random.default_rng(0).permutation(len(lines) - 1)[:3000]) + 1
        data = Path(out) / "A3000.csv"
        data.parent.mkdir(parents=True, exist_ok=True)
        data.write_text("\n".join([lines[0]] + [lines[i] for i in rows]) + "\n")
        argv = ["fit", "--robot", str(root / "ipa-ur10-tmac" / "robot.yaml"), "--data", str(data),
                "--out", str(Path(out) / "model"), "progress=false"]
        if case.endswith("geometry"):
            argv += ["residual=none", "gravity_compliance=none", "joint_harmonics=none"]
    else:
        argv = ["fit", "--robot", str(root / "jacobi-ur5-gts3800" / "robot.yaml"),
                "--data", str(root / "jacobi-ur5-gts3800" / "poses.csv"), "--out", str(Path(out) / "model"),
                "progress=false"]
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        main(argv)
    total_w, total_c = time.perf_counter() - w0, time.process_time() - c0
    wall["rest"] = total_w - sum(wall.values())
    cpu["rest"] = total_c - sum(cpu.values())
    import torchcal

    # which source ran: the baseline tree given, or the installed one (checked, not assumed)
    source = "baseline" if tree and Path(torchcal.__file__).is_relative_to(tree) else "installed"
    print(json.dumps({"wall": wall, "cpu": cpu, "total_wall": total_w, "total_cpu": total_c, "torchcal": source}))


CASES = {
    "twin": "`torchcal run` (default twin)",
    "ur10-A3000": "`torchcal fit`, UR10 series A, 3000 seeded rows",
    "ur10-A3000-geometry": "`torchcal fit`, UR10 series A, 3000 seeded rows, geometry alone "
                           "(`residual=none gravity_compliance=none joint_harmonics=none`)",
    "ur5-1000": "`torchcal fit`, UR5, 1000 poses",
}


def _run(case: str, tree: str | None, data_root: str) -> dict:
    env = dict(os.environ)
    if tree is not None:
        env["TORCHCAL_TREE"] = tree
    with tempfile.TemporaryDirectory() as tmp:
        load = os.getloadavg()[0]
        out = subprocess.run([sys.executable, __file__, "--child", case, "--data-root", data_root, "--out", tmp],
                             check=True, capture_output=True, text=True, env=env)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    result["load_before"] = load
    return result


def _median(runs: list[dict], key: str, stage: str | None = None) -> float:
    values = [r[key].get(stage, 0.0) if stage is not None else r[key] for r in runs]
    return statistics.median(values)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data-root", default=str(ROOT.parent / "shared" / "data" / "real"))
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--cases", nargs="*", default=list(CASES))
    parser.add_argument("--baseline", default=None, help="source tree of the version to compare with")
    parser.add_argument("--out", default=str(ROOT / "docs"))
    parser.add_argument("--collect", action="store_true",
                        help="no new runs: tabulate those earlier invocations saved under OUT/profile_fit_runs")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        _child(args.child, args.data_root, args.out)
        return
    from torchcal.core.io import atomic_write_json, atomic_write_text

    trees = {"this tree": None} | ({"baseline": args.baseline} if args.baseline else {})
    runs: dict[str, dict[str, list[dict]]] = {c: {t: [] for t in trees} for c in args.cases}
    saved = Path(args.out) / "profile_fit_runs"
    saved.mkdir(parents=True, exist_ok=True)
    for k in range(args.repeats):
        for case in args.cases:
            for tree, path in trees.items():
                file = saved / f"{case}__{tree.replace(' ', '-')}__{k}.json"
                if args.collect:  # only the runs saved by earlier invocations
                    if not file.exists():
                        continue
                    r = json.loads(file.read_text())
                else:
                    r = _run(case, path, args.data_root)
                    atomic_write_json(file, r)
                runs[case][tree].append(r)
                print(f"{case} [{tree}] run {k + 1}: {r['total_wall']:.1f} s wall, {r['total_cpu']:.1f} s CPU, "
                      f"load {r['load_before']:.1f}", flush=True)
    stages = list(dict.fromkeys(s for _, _, s in STAGES)) + ["rest"]
    lines = ["# Where a fit's time goes", "",
             f"`scripts/profile_fit.py`: median of the runs listed under each table (up to {args.repeats}), each a fresh "
             "process; wall and "
             "CPU (all threads) seconds per stage, exclusive of nested stages. Load average (1 min) before "
             "each run in the last column: the machine has 2 cores shared with other work, so wall times "
             "move with load; CPU seconds move less.", ""]
    for case in args.cases:
        for tree in trees:
            rs = runs[case][tree]
            if not rs:
                continue
            lines += [f"## {CASES[case]}: {tree}", "", "| stage | wall [s] | CPU [s] |", "|---|---:|---:|"]
            for stage in stages:
                w, c = _median(rs, "wall", stage), _median(rs, "cpu", stage)
                if w > 0.005 or c > 0.005:
                    lines.append(f"| {stage} | {w:.1f} | {c:.1f} |")
            lines.append(f"| **total** | **{_median(rs, 'total_wall'):.1f}** | **{_median(rs, 'total_cpu'):.1f}** |")
            lines += ["", "runs (wall s / load): " + ", ".join(f"{r['total_wall']:.1f} / {r['load_before']:.1f}"
                                                             for r in rs), ""]
    atomic_write_json(Path(args.out) / "profile_fit.json", {"cases": args.cases, "repeats": args.repeats,
                                                            "trees": list(trees), "runs": runs})
    atomic_write_text(Path(args.out) / "profile_fit.md", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
