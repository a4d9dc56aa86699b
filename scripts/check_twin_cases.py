"""``torchcal check`` on the twin after known changes: how often each verdict and name comes out.

A default fit (``residual=none``) of 300 poses of ``TwinConfig(seed=3)``; then, per case, the true
robot changed (or not) and ``--repeats`` checks of 12 new poses with new noise each.

    python scripts/check_twin_cases.py [--repeats 20] [--cases nothing,tool,theta3,link3,moved]

Prints one line per case (the figures of docs/lifecycle.md).
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
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.pipeline import fit_model
from torchcal.stages.store import load_model

MM, DEG = 1e-3, math.pi / 180


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--cases", default="nothing,tool,theta3,link3,moved")
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    twin = Twin.create(TwinConfig(seed=3))
    train = twin.sample(300, torch.Generator().manual_seed(11))
    cases = {
        "nothing": twin,
        "tool": twin.changed(tool_x=1.0 * MM, tool_y=-0.5 * MM, tool_z=2.0 * MM),
        "theta3": twin.changed(theta3=0.05 * DEG),
        "link3": twin.changed(alpha3=0.05 * DEG, a3=0.3 * MM),
        "moved": twin.changed(base_x=50 * MM, base_y=-20 * MM, base_rz=1.0 * DEG),
    }
    with tempfile.TemporaryDirectory() as tmp:
        fit_model(Path(tmp) / "model", twin.robot, train, FitConfig(residual="none", progress=False))
        stored = load_model(Path(tmp) / "model")
        for name in args.cases.split(","):
            verdicts, named = Counter(), Counter()
            start = time.perf_counter()
            for r in range(args.repeats):
                result = check_data(stored, cases[name].sample(12, torch.Generator().manual_seed(1000 + r)))
                verdicts[result.verdict] += 1
                named[",".join(result.changed) or "-"] += 1
            print(f"{name}: {dict(verdicts)} named {named.most_common(4)} "
                  f"({(time.perf_counter() - start) / args.repeats:.2f} s per check)")


if __name__ == "__main__":
    main()
