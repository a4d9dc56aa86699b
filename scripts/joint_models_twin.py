"""Learned joint-space models on the twin: ``python scripts/joint_models_twin.py``.

Two twins of ``torchcal run``'s size (1500 training, 600 held-out poses): the default one
(gravity compliance, gear errors of two harmonics) and one with gear errors of three harmonics and
a nonlinear compliance (``gear_orders=3``, ``compliance_cubic=0.5``). Each is fitted with the
default structure selection (``auto``: classic and learned joint-space models in competition;
residual heads off, they are refused on both) and with first harmonics alone
(``joint_harmonics=first``, gravity still chosen) and with the cubic compliance and a series of
order 3 given explicitly; the held-out RMS of each against the twin's
noise floor goes to ``docs/joint_models_twin.md``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import torch

from torchcal.config.schema import FitConfig
from torchcal.core.errors import IdentifiabilityWarning
from torchcal.core.io import atomic_write_text
from torchcal.identify.joint_fit import predicted_positions
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit

TWINS = {"default twin (gear orders 1-2, linear compliance)": {},
         "gear orders 1-3, compliance_cubic=0.5": {"gear_orders": 3, "compliance_cubic": 0.5}}
# the default twin's default fit is what `torchcal run` prints (scripts/bench_run_joint_models.py)
FITS = {"default (auto)": {}, "first harmonics alone": {"joint_harmonics": "first"},
        "cubic compliance + fourier3 (explicit)": {"gravity_compliance": "elbow+wrist+cubic", "joint_harmonics": "fourier3",
                                                   "uncertainty": "none"}}


def main() -> None:
    lines = ["# Learned joint-space models on the twin", "",
             "`python scripts/joint_models_twin.py`: 1500 training and 600 held-out poses (seed 0, as `torchcal run`), "
             "residual heads off; held-out 3-D RMS against the noise floor.", "",
             "| twin | fit | chosen structure | held-out RMS [mm] | x noise floor | fit [s] |", "|---|---|---|---|---|---|"]
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--twins", default="", help="indices into TWINS to run (default: all), comma-separated")
    parser.add_argument("--out", default="docs/joint_models_twin.md")
    args = parser.parse_args()
    chosen_twins = {int(i) for i in args.twins.split(",") if i} or set(range(len(TWINS)))
    for t, (twin_name, extra) in enumerate(TWINS.items()):
        if t not in chosen_twins:
            continue
        cfg = TwinConfig(gravity=True, gear=True, n_train=1500, n_test=600, **extra)
        twin = Twin.create(cfg)
        gen = torch.Generator().manual_seed(cfg.seed + 7919)  # as write_twin_case draws them
        train, test = twin.sample(cfg.n_train, gen), twin.sample(cfg.n_test, gen)
        for fit_name, options in FITS.items():
            start = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", IdentifiabilityWarning)
                result = fit(twin.robot, train, FitConfig(**{"residual": "none", "uncertainty": "none", "progress": False,
                                                             **options}))
            seconds = time.perf_counter() - start
            rms = float((test.position - predicted_positions(result, test.q)).norm(dim=-1).pow(2).mean().sqrt()) * 1e3
            chosen = next((n.split(" -> ")[-1] for n in result.notes if n.startswith("structure chosen")), "")
            lines.append(f"| {twin_name} | {fit_name} | {chosen} | {rms:.4f} | {rms / cfg.noise_floor_rms_mm:.2f} | "
                         f"{seconds:.0f} |")
            print(lines[-1], flush=True)
    atomic_write_text(args.out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
