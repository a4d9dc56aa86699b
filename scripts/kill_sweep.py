"""Stop ``torchcal fit | export | evaluate --report | simulate | run`` with a signal at spread-out moments.

Each trial restores an earlier result at the output path, starts the command that replaces it,
sends the signal (``KILL``: ``kill -9``; ``TERM``: a job scheduler or ``systemctl stop``; ``INT``:
Ctrl-C) after ``t_i = 1.25 T (i - 0.5) / n`` seconds (``T``: the shorter of two uninterrupted
runs, measured first) and checks that the output holds the earlier result or the new one, whole:
for a model or export folder ``checksums.json`` verifies, the folder loads (``load_model``; the
ONNX files' hashes against ``manifest.json``) and its file list is the earlier or the new one's;
for a report, twin case or run folder, its files are byte for byte the earlier ones or the new ones
(figures and timings aside: their names must match).

    python scripts/kill_sweep.py --kind fit --signal TERM --n 20 --work /tmp/kill_fit

Prints one line per trial and a final ``N of N whole`` line; exit status 1 if any trial failed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

CLI = [sys.executable, "-m", "torchcal.cli"]
#: Kill times cover this multiple of the uninterrupted duration, so that the last ones land in or after the commit.
SPAN = 1.25


def run(args: list[str]) -> None:
    subprocess.run(CLI + args, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def checksums(folder: Path) -> dict[str, str]:
    return json.loads((folder / "checksums.json").read_text())["files"]


def whole(kind: str, folder: Path) -> str:
    """``""`` when ``folder`` is whole and verifiable, else why not."""
    from torchcal.core.errors import TorchcalError
    from torchcal.core.folder import verify_folder
    from torchcal.core.hashing import sha256_file

    if not folder.is_dir():
        return "absent"
    if kind not in ("fit", "export"):
        return ""  # unsealed folders: judged by their contents against the earlier and the new one
    try:
        verify_folder(folder)
        if kind == "fit":
            from torchcal.stages.store import load_model

            load_model(folder)
        else:
            manifest = json.loads((folder / "manifest.json").read_text())
            for key, name in manifest["files"].items():
                if sha256_file(folder / name) != manifest["sha256"][key]:
                    return f"{name} differs from manifest.json"
    except (TorchcalError, OSError, ValueError, KeyError) as exc:
        return str(exc)
    return ""


def contents(kind: str, folder: Path) -> dict[str, str]:
    """What identifies a result: the checksum list of a sealed folder, else each file's SHA-256
    (names only for figures and files holding timings, which differ between two identical runs)."""
    from torchcal.core.hashing import sha256_file

    if kind in ("fit", "export"):
        return checksums(folder)
    varying = ("figures/", "metrics.json", "report.md", "report.html", ".torchcal-output", "model/")
    return {p.relative_to(folder).as_posix(): ("" if p.relative_to(folder).as_posix().startswith(varying)
                                                else sha256_file(p))
            for p in sorted(folder.rglob("*")) if p.is_file()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kind", choices=["fit", "export", "evaluate-report", "simulate", "run"], required=True)
    parser.add_argument("--signal", choices=["KILL", "TERM", "INT"], default="KILL")
    parser.add_argument("--n", type=int, default=20)
    parser.add_argument("--work", type=Path, required=True)
    args = parser.parse_args()
    sig = getattr(signal, f"SIG{args.signal}")
    work = args.work
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    case = work / "case"
    run(["simulate", "--out", str(case), "n_train=40", "n_test=20", "gravity=true"])
    robot, data = str(case / "robot.yaml"), str(case / "train.csv")
    earlier, out = work / "earlier", work / "out"
    fast = ["residual=none", "gravity_compliance=none", "joint_harmonics=none"]
    if args.kind == "fit":
        # earlier: geometry only; new: the default fit (structure CV, residual heads)
        run(["fit", "--robot", robot, "--data", data, "--out", str(earlier), *fast])
        command = CLI + ["fit", "--robot", robot, "--data", data, "--out", str(out), "residual=elm"]
    elif args.kind == "export":
        model = work / "model"
        run(["fit", "--robot", robot, "--data", data, "--out", str(model), *fast])
        run(["export", "--model", str(model), "--out", str(earlier), "--iterations", "2", "--portable"])
        command = CLI + ["export", "--model", str(model), "--out", str(out)]
    elif args.kind == "evaluate-report":
        model = work / "model"
        run(["fit", "--robot", robot, "--data", data, "--out", str(model), *fast])
        run(["evaluate", "--model", str(model), "--data", data, "--report", str(earlier)])
        command = CLI + ["evaluate", "--model", str(model), "--data", str(case / "test.csv"), "--report", str(out)]
    elif args.kind == "simulate":
        run(["simulate", "--out", str(earlier), "seed=1", "n_train=3000"])
        command = CLI + ["simulate", "--out", str(out), "seed=2", "n_train=3000"]
    else:
        # a run folder is out/<name>: earlier and new differ in their twin
        runs = work / "runs"
        small = ["twin.n_train=60", "twin.n_test=30", "export=false", "fit.residual=none", f"out={runs}"]
        run(["run", *small, "name=earlier", "twin.seed=1"])
        earlier, out = runs / "earlier", runs / "out"
        command = CLI + ["run", *small, "name=out", "twin.seed=2"]
    durations = []
    for _ in range(2):  # the shorter of two runs, so that the later kill times still land inside a run
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(earlier, out)
        started = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        durations.append(time.perf_counter() - started)
    duration = min(durations)
    new_files = contents(args.kind, out)
    old_files = contents(args.kind, earlier)
    print(f"{args.kind}, SIG{args.signal}: uninterrupted {duration:.1f} s; earlier {sorted(old_files)}; new {sorted(new_files)}")
    good = killed = 0
    for i in range(1, args.n + 1):
        shutil.rmtree(out)
        shutil.copytree(earlier, out)
        at = SPAN * duration * (i - 0.5) / args.n
        proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                # a shell without job control starts background commands with SIGINT ignored
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            proc.wait(timeout=at)
            state = "finished before the kill"
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, sig)
            proc.wait()
            state = f"SIG{args.signal} sent"
            killed += 1
        why = whole(args.kind, out)
        leftovers = [p.name for p in out.parent.iterdir() if ".staging-" in p.name]
        if not why and leftovers and sig != signal.SIGKILL:  # a handled signal cleans its staging folder up
            why = f"staging folder left: {leftovers[0]}"
        if not why:
            files = contents(args.kind, out)
            same_names = args.kind in ("fit", "export")  # a sealed folder's new files differ by run (timings)
            which = ("earlier" if files == old_files else
                     "new" if (set(files) == set(new_files) if same_names else files == new_files) else "")
            why = "" if which else f"file list {sorted(files)} is neither the earlier nor the new one"
        ok = not why
        good += ok
        print(f"  t={at:6.2f} s {state:25s} -> {'whole, ' + which if ok else 'BROKEN: ' + why}", flush=True)
    print(f"{args.kind}, SIG{args.signal}: {good} of {args.n} signal times leave a whole, verifiable result "
          f"({killed} stopped mid-run, {args.n - killed} finished first)")
    return 0 if good == args.n else 1


if __name__ == "__main__":
    raise SystemExit(main())
