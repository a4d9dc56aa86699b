"""Kill ``torchcal fit`` / ``torchcal export`` with SIGKILL at spread-out moments; check the folder.

Each trial restores an earlier result in the output folder, starts the command that replaces it,
kills it with ``kill -9`` after ``t_i = 1.25 T (i - 0.5) / n`` seconds (``T``: the shorter of two
uninterrupted runs, measured first) and checks that the output folder holds the earlier result or
the new one, whole: ``checksums.json`` verifies, the folder loads (``load_model`` for a fit; the
ONNX files' hashes against ``manifest.json`` for an export), and its file list is the earlier
one's or the new one's.

    python scripts/kill_sweep.py --kind fit --n 20 --work /tmp/kill_fit
    python scripts/kill_sweep.py --kind export --n 20 --work /tmp/kill_export

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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kind", choices=["fit", "export"], required=True)
    parser.add_argument("--n", type=int, default=20)
    parser.add_argument("--work", type=Path, required=True)
    args = parser.parse_args()
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
    else:
        model = work / "model"
        run(["fit", "--robot", robot, "--data", data, "--out", str(model), *fast])
        run(["export", "--model", str(model), "--out", str(earlier), "--iterations", "2", "--portable"])
        command = CLI + ["export", "--model", str(model), "--out", str(out)]
    durations = []
    for _ in range(2):  # the shorter of two runs, so that the later kill times still land inside a run
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(earlier, out)
        started = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        durations.append(time.perf_counter() - started)
    duration = min(durations)
    new_files = checksums(out)
    old_files = checksums(earlier)
    print(f"{args.kind}: uninterrupted {duration:.1f} s; earlier {sorted(old_files)}; new {sorted(new_files)}")
    good = killed = 0
    for i in range(1, args.n + 1):
        shutil.rmtree(out)
        shutil.copytree(earlier, out)
        at = SPAN * duration * (i - 0.5) / args.n
        proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            proc.wait(timeout=at)
            state = "finished before the kill"
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
            state = "killed"
            killed += 1
        why = whole(args.kind, out)
        if not why:
            files = checksums(out)
            which = "earlier" if files == old_files else "new" if set(files) == set(new_files) else ""
            why = "" if which else f"file list {sorted(files)} is neither the earlier nor the new one"
        ok = not why
        good += ok
        print(f"  t={at:6.2f} s {state:25s} -> {'whole, ' + which if ok else 'BROKEN: ' + why}", flush=True)
    print(f"{args.kind}: {good} of {args.n} kill times leave a whole, verifiable folder "
          f"({killed} killed mid-run, {args.n - killed} finished first)")
    return 0 if good == args.n else 1


if __name__ == "__main__":
    raise SystemExit(main())
