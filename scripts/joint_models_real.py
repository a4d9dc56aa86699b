"""Learned joint-space models on the real sets: ``python scripts/joint_models_real.py --data-root ../shared/data/real``.

Runs the UR10 transfers (A -> C and D, C -> B, B -> C, re-registered) and the IRB 120 grouped CV
of :mod:`torchcal.app.validation` with the fit's structure selection (``joint_harmonics=auto``,
``gravity_compliance=auto``: the classic options and the learned joint-space models in
competition, residual heads off: they are refused on every one of these rows), and writes per row
the held-out RMS, the gate's choice and its CV table to ``docs/joint_models_real.json``. With
``--forced`` each learned option is fitted instead of the gate (what it would have done;
``--out docs/joint_models_real_forced.json``; ``--options G:H,...`` forces those pairs instead). Today's default: the same script run on that
revision (``git archive``; its package first on ``PYTHONPATH``).
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import torch

from torchcal.app.validation import PROTOCOLS, _fit_and_score, _pairs, _structure_name
from torchcal.config.schema import FitConfig
from torchcal.core.errors import IdentifiabilityWarning
from torchcal.core.io import atomic_write_json
from torchcal.data.measurements import load_measurements
from torchcal.identify.joint_fit import LEARNED_OPTIONS
from torchcal.kinematics.robot import load_robot

ROWS = ("C_to_B", "B_to_C", "A_to_CD", "icelinker-irb120-faro")


def _protocols(names) -> list:
    """The protocols of ``names`` (a transfer's slug or a data set's grouped CV), in that order."""
    return [p for name in names for p in PROTOCOLS
            if p.slug_name == name or (p.dataset == name and p.label.startswith("grouped"))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data-root", default="../shared/data/real")
    parser.add_argument("--out", default="docs/joint_models_real.json")
    parser.add_argument("--only", default="", help="comma-separated slugs (default: every row)")
    parser.add_argument("--forced", action="store_true",
                        help="fit each learned option of the gate (LEARNED_OPTIONS) forced, instead of the gate, to show "
                             "what it would have done")
    parser.add_argument("--options", default="",
                        help="with --forced: comma-separated GRAVITY:HARMONICS pairs to force instead of LEARNED_OPTIONS, "
                             "e.g. elbow+wrist:first,elbow+forearm+wrist:first")
    args = parser.parse_args()
    root, results = Path(args.data_root), []
    forced = [tuple(o.split(":", 1)) for o in args.options.split(",") if o] or list(LEARNED_OPTIONS)
    configs = ({f"{g}+{h}": FitConfig(residual="none", uncertainty="none", progress=False, gravity_compliance=g,
                                      joint_harmonics=h) for g, h in forced}
               if args.forced else {"default (gate)": FitConfig(residual="none", progress=False)})
    for protocol in _protocols(list(filter(None, args.only.split(","))) or ROWS):
        start = time.perf_counter()
        folder = root / protocol.dataset
        robot = load_robot(folder / "robot.yaml")
        data = load_measurements(folder / protocol.fit_file, robot)
        for config_name, config in configs.items():
            errors: dict[int, list] = {}
            choices, tables = [], []
            with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
                warnings.simplefilter("ignore", IdentifiabilityWarning)
                for i, (train, tests) in enumerate(_pairs(data, protocol, robot, folder, 0)):
                    out = _fit_and_score(robot, train, tests, protocol, config, Path(tmp) / f"m{i}")
                    for k, e in enumerate(out["errors"]):
                        errors.setdefault(k, []).append(e)
                    choices.append(_structure_name(out["result"]))
                    tables.append(out["structure_note"])
            labels = list(protocol.test_files) or ["held out"]
            row = {"dataset": protocol.dataset, "protocol": protocol.label, "fit": config_name, "choices": choices,
                   "cv_tables": tables, "seconds": time.perf_counter() - start,
                   "rms_mm": {labels[k]: float((torch.cat(v).norm(dim=-1) * 1e3).pow(2).mean().sqrt())
                              for k, v in errors.items()}}
            print(row["dataset"], row["protocol"][:40], config_name, row["rms_mm"], choices, f"{row['seconds']:.0f} s",
                  flush=True)
            results.append(row)
        atomic_write_json(Path(args.out), results)


if __name__ == "__main__":
    main()
