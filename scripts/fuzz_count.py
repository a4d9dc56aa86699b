"""Run the bad-input cases of ``torchcal/testing/fuzz_cases.py`` as processes against a checkout and count outcomes.

    python scripts/fuzz_count.py --checkout /path/to/torchcal --work /tmp/fuzz_count

The inputs are built with this checkout; each command runs as ``python -m torchcal.cli`` with
``PYTHONPATH=<checkout>``, so the same cases can be counted before and after a change. Each case
is classed as

* ``one line``: exit 2 (or 130) with exactly one ``torchcal: error:`` line and no traceback;
* ``warned``: exit 0 with a ``torchcal: warning:`` line holding the case's expected text;
* ``traceback``: a Python traceback on stderr;
* ``silent``: exit 0 with no such warning (a result from bad data);
* ``other``: anything else (another exit status, several error lines).

``as expected`` additionally needs the case's own exit status, text and output-path state.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

from torchcal.testing.fuzz_cases import (
    CASES,
    CLASSES,
    Case,
    make_fixtures,
    out_state_problem,
    snapshot,
)

HERE = Path(__file__).resolve().parents[1]


def _nonblank(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip()]


def print_case(name: str, rc: int, kind: str, ok: bool, last: str, state: str = "") -> None:
    """One result line: case, exit status, class, verdict, what went wrong with the output, last message."""
    print(f"{name:32s} rc={rc:<3d} {kind:9s} {'as expected' if ok else 'NOT as expected'}"
          f"{'; ' + state if state else ''} | {last[:150]}", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkout", type=Path, required=True, help="repository root whose torchcal runs the commands")
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--only", nargs="*", default=None, help="case names, ctrl_c included (default: all)")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds a case may run (then: timeout)")
    args = parser.parse_args()
    args.work = args.work.resolve()
    env = {**os.environ, "PYTHONPATH": str(args.checkout.resolve())}

    def run(argv: list[str], file_limit: int | None = None) -> subprocess.CompletedProcess:
        def limit() -> None:
            if file_limit is not None:
                import resource

                resource.setrlimit(resource.RLIMIT_FSIZE, (file_limit, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
        return subprocess.run([sys.executable, "-m", "torchcal.cli", *argv], capture_output=True, text=True, env=env, cwd=args.work,
                              timeout=args.timeout, preexec_fn=limit)

    shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True)
    from torchcal.cli import main as here_main

    fixtures = make_fixtures(args.work / "fixtures", lambda argv: here_main(argv))
    classes: Counter[str] = Counter()
    by_class: dict[str, Counter[str]] = {}
    expected = 0
    for name in [n for n in args.only or sorted(CASES) if n in CASES]:
        work = args.work / name
        work.mkdir()
        case = CASES[name](fixtures, work)
        before = snapshot(case.out)
        try:
            proc = run(case.argv, case.extra.get("file_limit"))
        except subprocess.TimeoutExpired:
            classes["timeout"] += 1
            print(f"{name:32s} rc=-   timeout   NOT as expected | still running after {args.timeout:g} s", flush=True)
            continue
        err = proc.stderr
        errors = [line for line in err.splitlines() if line.startswith("torchcal: error:")]
        warned = [line for line in err.splitlines() if line.startswith("torchcal: warning:") and case.message in line]
        if "Traceback" in err:
            kind = "traceback"
        elif proc.returncode in (2, 130) and len(errors) == 1:
            kind = "one line"
        elif proc.returncode == 0 and warned:
            kind = "warned"
        elif proc.returncode == 0:
            kind = "silent"
        else:
            kind = "other"
        state = out_state_problem(case, before)
        ok = (proc.returncode == case.rc and not state
              and (any(case.message in e for e in errors) if case.rc else bool(warned)))
        expected += ok
        classes[kind] += 1
        tally = by_class.setdefault(CLASSES.get(name, "bad input files"), Counter())
        tally["cases"] += 1
        tally["as expected"] += ok
        print_case(name, proc.returncode, kind, ok, (errors or _nonblank(err) or [""])[-1], state)
    if args.only is None or "ctrl_c" in args.only:
        # Ctrl-C into a refit over an earlier model folder at 25, 50 and 75 % of an uninterrupted
        # refit's duration (measured first): while fitting, while learning heads, while writing
        import signal
        import time

        refit = [sys.executable, "-m", "torchcal.cli", "fit", "--robot", str(fixtures.robot), "--data",
                 str(fixtures.train), "--out"]
        started = time.perf_counter()
        subprocess.run([*refit, str(args.work / "ctrl_c_timing")], capture_output=True, env=env, cwd=args.work, check=True)
        duration = time.perf_counter() - started
        for sig, status, word in ((signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")):
            for share in (0.25, 0.5, 0.75):
                name = f"{signal.Signals(sig).name}@{share:.0%}"
                out = args.work / name / "model"
                shutil.copytree(fixtures.model, out)
                before = snapshot(out)
                proc = subprocess.Popen([*refit, str(out)], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                        text=True, env=env, cwd=args.work,
                                        # a shell without job control starts background commands with SIGINT ignored
                                        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
                time.sleep(share * duration)
                proc.send_signal(sig)
                err = proc.communicate(timeout=600)[1]
                # a process that ends by the signal itself (within a second of its start) shows 128 + signal in a shell too
                stopped = proc.returncode in (status, -sig)
                # under a varying load the refit may end before the signal arrives: then its new folder must be whole
                finished = proc.returncode == 0 and not out_state_problem(Case([], 0, "", out, "whole"), before)
                kind = ("traceback" if "Traceback" in err else "one line" if stopped else
                        "finished first" if finished else "other")
                ok = (stopped and (word in err or proc.returncode == -sig) and snapshot(out) == before) or finished
                expected += ok
                classes[kind] += 1
                tally = by_class.setdefault("termination", Counter())
                tally["cases"] += 1
                tally["as expected"] += ok
                print_case(name, proc.returncode, kind, ok, (_nonblank(err) or [""])[-1])
    for cls, tally in sorted(by_class.items()):
        print(f"  {cls}: {tally['as expected']} of {tally['cases']} as expected")
    total = sum(classes.values())
    print(f"{total} cases: " + ", ".join(f"{k} {v}" for k, v in sorted(classes.items()))
          + f"; as expected (status, text, output state) {expected} of {total}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
