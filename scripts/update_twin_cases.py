"""``torchcal update`` on the twin after known changes: 12 poses against a full 300-pose refit.

A default fit (``residual=none``) of 300 poses of ``TwinConfig(seed=3)`` is the old model. Per case
the true robot is changed (or not); then

* ``update`` (default ``free=auto``) from 12 new poses with new noise, ``--repeats`` times;
* a full default fit of 300 new poses of the changed robot (its own frame), once;

both scored on 500 held-out poses of the changed robot, each in its own instrument frame (what
a user gets; the tracker has not moved since those poses) and re-registered to the held-out poses.

    python scripts/update_twin_cases.py [--repeats 5] [--cases nothing,moved,tool,theta3,link3,tool+theta2]

Prints one line per case and writes docs/update_twin_cases.md (the figures of docs/lifecycle.md).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
import warnings
from collections import Counter
from pathlib import Path

import torch

from torchcal.app.update import update_data, write_update
from torchcal.config.schema import FitConfig
from torchcal.core.folder import staged_folder
from torchcal.core.io import atomic_write_text
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import held_out_errors
from torchcal.stages.pipeline import fit_model
from torchcal.stages.store import load_model

MM, DEG = 1e-3, 3.141592653589793 / 180
CHANGES = {
    "nothing": {},
    "moved": {"base_x": 50 * MM, "base_y": -20 * MM, "base_rz": 1.0 * DEG},
    "tool": {"tool_x": 1.0 * MM, "tool_y": -0.5 * MM, "tool_z": 2.0 * MM},
    "theta3": {"theta3": 0.05 * DEG},
    "link3": {"alpha3": 0.05 * DEG, "a3": 0.3 * MM},
    "tool+theta2": {"tool_x": 1.0 * MM, "tool_y": -0.5 * MM, "tool_z": 2.0 * MM, "theta2": 0.05 * DEG},
}


def rms(errors: torch.Tensor) -> float:
    return float(errors.norm(dim=-1).pow(2).mean().sqrt()) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--cases", default=",".join(CHANGES))
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs"))
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    twin = Twin.create(TwinConfig(seed=3))
    config = FitConfig(residual="none", progress=False)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        fit_model(Path(tmp) / "old", twin.robot, twin.sample(300, torch.Generator().manual_seed(11)), config)
        old = load_model(Path(tmp) / "old")
        for name in args.cases.split(","):
            robot = twin.changed(**CHANGES[name])
            test = robot.sample(500, torch.Generator().manual_seed(77))
            fit_model(Path(tmp) / f"full_{name}", robot.robot, robot.sample(300, torch.Generator().manual_seed(12)), config)
            full = load_model(Path(tmp) / f"full_{name}")
            full_own, full_reg = rms(held_out_errors(full, test)), rms(held_out_errors(full, test, register=True))
            own, reg, freed, seconds = [], [], Counter(), []
            for r in range(args.repeats):
                started = time.perf_counter()
                result = update_data(old, robot.sample(12, torch.Generator().manual_seed(2000 + r)))
                seconds.append(time.perf_counter() - started)
                with staged_folder(Path(tmp) / f"upd_{name}_{r}") as staging:
                    write_update(staging, result)
                new = load_model(Path(tmp) / f"upd_{name}_{r}")
                own.append(rms(held_out_errors(new, test)))
                reg.append(rms(held_out_errors(new, test, register=True)))
                freed[",".join(result.freed) or "frame only"] += 1
            row = {"case": name, "full_own": full_own, "full_reg": full_reg, "own_median": statistics.median(own),
                   "own_worst": max(own), "reg_median": statistics.median(reg), "freed": dict(freed),
                   "seconds": statistics.median(seconds), "old_reg": rms(held_out_errors(old, test, register=True))}
            rows.append(row)
            print(row)
    lines = ["| situation | old model, re-registered | full refit (300 poses), own frame | update (12 poses), own frame: "
             f"median / worst of {args.repeats} | ratio (median) | update, re-registered (median) | freed | update time |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['old_reg']:.4f} | {r['full_own']:.4f} | {r['own_median']:.4f} / {r['own_worst']:.4f} | "
                     f"{r['own_median'] / r['full_own']:.2f} | {r['reg_median']:.4f} | "
                     f"{'; '.join(f'{k} {v}' for k, v in r['freed'].items())} | {r['seconds']:.1f} s |")
    text = ("# `torchcal update` on the twin\n\nMade by `scripts/update_twin_cases.py` (its docstring states the protocol). "
            "RMS in mm on 500 held-out poses of the changed robot.\n\n" + "\n".join(lines) + "\n")
    atomic_write_text(Path(args.out) / "update_twin_cases.md", text)
    print(text)


if __name__ == "__main__":
    main()
