"""``torchcal check`` on the twin after known changes: how often each verdict and name comes out.

A default fit (``residual=none``) of 300 poses of ``TwinConfig(seed=3)``; then, per case, the true
robot changed (or not) and checks of 12 new poses with new noise each (``default_rng`` seeds
``1000 + r``): ``--unchanged-repeats`` on the unchanged robot (the false-alarm rate), ``--repeats``
on each changed one.

    python scripts/check_twin_cases.py [--repeats 20] [--unchanged-repeats 100] [--cases nothing,tool,theta3,link3,moved]

Prints one line per case and writes docs/check_twin_cases.md and .json (the figures of docs/lifecycle.md).
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
import warnings
from collections import Counter
from pathlib import Path

import torch

from torchcal.app.check import check_data
from torchcal.config.schema import FitConfig
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.pipeline import fit_model
from torchcal.stages.store import load_model

MM, DEG = 1e-3, math.pi / 180
#: Per case: the change to the true robot and the names a correct check gives (None: no change to name).
CASES = {
    "nothing": ({}, None),
    "moved": ({"base_x": 50 * MM, "base_y": -20 * MM, "base_rz": 1.0 * DEG}, None),
    "tool": ({"tool_x": 1.0 * MM, "tool_y": -0.5 * MM, "tool_z": 2.0 * MM}, "tool"),
    "theta3": ({"theta3": 0.05 * DEG}, "theta3"),
    "link3": ({"alpha3": 0.05 * DEG, "a3": 0.3 * MM}, "alpha3,a3,beta3"),
}
DESCRIPTION = {
    "nothing": ("nothing changed", "none"),
    "moved": ("robot moved", "base +50 mm x, -20 mm y, +1 deg about z"),
    "tool": ("tool swapped", "tool +1.0, -0.5, +2.0 mm"),
    "theta3": ("joint 3 re-mastered", "theta3 +0.05 deg"),
    "link3": ("link 3 bent", "alpha3 +0.05 deg, a3 +0.3 mm"),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--unchanged-repeats", type=int, default=100)
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs"))
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    twin = Twin.create(TwinConfig(seed=3))
    train = twin.sample(300, torch.Generator().manual_seed(11))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        fit_model(Path(tmp) / "model", twin.robot, train, FitConfig(residual="none", progress=False))
        stored = load_model(Path(tmp) / "model")
        for name in args.cases.split(","):
            change, expected = CASES[name]
            robot = twin.changed(**change)
            repeats = args.unchanged_repeats if not change else args.repeats
            verdicts, named = Counter(), Counter()
            start = time.perf_counter()
            for r in range(repeats):
                result = check_data(stored, robot.sample(12, torch.Generator().manual_seed(1000 + r)))
                verdicts[result.verdict] += 1
                named[",".join(result.changed) or "-"] += 1
            # a changed case counts right only where the verdict is changed and names exactly the changed group
            right = verdicts["valid"] if expected is None else named[expected]
            row = {"case": name, "repeats": repeats, "verdicts": dict(verdicts), "named": dict(named),
                   "expected": "valid" if expected is None else f"changed: {expected}", "right": right,
                   "seconds_per_check": (time.perf_counter() - start) / repeats}
            rows.append(row)
            print(row, flush=True)
    lines = ["| situation | change to the true robot | checks | right | verdicts | named | time per check |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        what, change = DESCRIPTION[r["case"]]
        verdicts = ", ".join(f"{k} {v}" for k, v in sorted(r["verdicts"].items(), key=lambda kv: -kv[1]))
        named = ", ".join(f"{k} {v}" for k, v in sorted(r["named"].items(), key=lambda kv: -kv[1]))
        lines.append(f"| {what} | {change} | {r['repeats']} | **{r['right']}** ({r['expected']}) | {verdicts} | "
                     f"{named} | {r['seconds_per_check']:.2f} s |")
    text = ("# `torchcal check` on the twin\n\nMade by `scripts/check_twin_cases.py` (its docstring states the protocol): "
            "`TwinConfig(seed=3)`, default fit of 300 poses with `residual=none`, each check 12 new poses with new "
            "noise. \"right\": `valid` on an unchanged (or only moved) robot, `changed` naming the changed group "
            "otherwise; \"named\" lists `changed` of `--json` (`-`: nothing named).\n\n" + "\n".join(lines) + "\n")
    atomic_write_text(Path(args.out) / "check_twin_cases.md", text)
    atomic_write_json(Path(args.out) / "check_twin_cases.json", {"results": rows})
    print(text)


if __name__ == "__main__":
    main()
