"""What the per-pose prediction uncertainty adds to ``evaluate``, on 10,000 poses.

Usage: python scripts/bench_uncertainty.py [--poses 10000] [--repeats 5] [--out docs/bench_uncertainty]

A twin (gravity and gear errors) is calibrated on the spot (geometry with the joint-space terms the
cross-validation chooses, no residual head) and a file of ``--poses`` random poses is scored by
:func:`torchcal.instruments.tracker.evaluate.evaluate`. Timed in the same run, median of
``--repeats``:

* the whole ``evaluate`` (file read, held-out errors, leakage, compensator check, uncertainty);
* the uncertainty alone, per method (``conformal``, ``gaussian``): the point Jacobian, the
  propagated covariance and the 95 % radii, then the coverage;
* the held-out errors alone (the model's prediction), the cost the uncertainty is set against.

Writes ``OUT.json`` and ``OUT.md`` (atomically).
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np


def _median_s(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--poses", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "bench_uncertainty"))
    args = parser.parse_args()

    import torch

    from torchcal.core.io import atomic_write_json, atomic_write_text
    from torchcal.data.measurements import load_measurements
    from torchcal.instruments.tracker.evaluate import evaluate
    from torchcal.instruments.tracker.twin_case import write_twin_case
    from torchcal.kinematics.robot import load_robot
    from torchcal.sim.twin import TwinConfig
    from torchcal.stages.geometry import held_out_errors
    from torchcal.stages.prediction_uncertainty import score, stored_prediction
    from torchcal.stages.store import load_model

    with tempfile.TemporaryDirectory() as tmp:
        case = write_twin_case(Path(tmp) / "case", TwinConfig(n_train=400, n_test=args.poses, gravity=True, gear=True))
        from torchcal.config.schema import FitConfig
        from torchcal.stages.geometry import fit_with_selection, save_fit

        config = FitConfig(residual="none", progress=False)
        robot = load_robot(case["robot.yaml"])
        train = load_measurements(case["train.csv"], robot)
        result, structure = fit_with_selection(robot, train, config)
        folder = save_fit(Path(tmp) / "model", robot, train, result, {}, structure=structure)
        stored = load_model(folder)
        test = load_measurements(case["test.csv"], robot)
        errors = held_out_errors(stored, test)
        rows = {
            "evaluate (whole command, uncertainty included)": _median_s(lambda: evaluate(folder, case["test.csv"]),
                                                                       args.repeats),
            "held-out errors alone (the model's prediction)": _median_s(lambda: held_out_errors(stored, test),
                                                                        args.repeats),
        }
        for method in ("conformal", "gaussian"):
            def run(method=method):
                prediction = stored_prediction(stored, test.q, method)
                assert prediction is not None
                return score(prediction, errors, method)

            rows[f"uncertainty, {method} (Jacobian, covariance, radii, coverage)"] = _median_s(run, args.repeats)
        coverage = {m: score(stored_prediction(stored, test.q, m), errors, m)["coverage_95"]  # type: ignore[arg-type]
                    for m in ("conformal", "gaussian")}
    machine = (f"{platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
               f"{torch.get_num_threads()} intra-op threads")
    lines = ["# Prediction uncertainty: time added to `evaluate`", "",
             f"Machine: {machine}. {args.poses} poses, median of {args.repeats} repeats after a warm-up "
             "(`python scripts/bench_uncertainty.py`).", "",
             "| step | median [s] |", "|---|---|"]
    lines += [f"| {name} | {seconds:.3f} |" for name, seconds in rows.items()]
    lines += ["", "Coverage of the 95 % region on these poses (twin, gravity and gear errors): "
              + ", ".join(f"{m} {100 * c:.1f} %" for m, c in coverage.items()) + "."]
    out = Path(args.out)
    atomic_write_json(out.with_suffix(".json"), {"machine": machine, "poses": args.poses, "repeats": args.repeats,
                                                 "median_s": rows, "coverage_95": coverage})
    atomic_write_text(out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
