"""``torchcal compensate`` on a 10,000-target program: time and largest correction.

A geometric model of the default twin (150 poses, ``residual=none``), a program of 10,000 joint
targets uniform within the joint limits (5 deg from each), corrected by ``compensate_program``
(the whole command: reading, the compensator in torch float64, the export's refusal check, writing
CSV and sidecar) and, as the alternative in the same run, by the same model's exported float64
ONNX compensator in onnxruntime (``CompensatorRuntime.correct_with_residual``, all cores, the
export itself not timed). Median of ``--repeats`` runs each.

    python scripts/bench_compensate_program.py [--out docs/bench_compensate_program] [--targets 10000]

Writes ``OUT.json`` and ``OUT.md`` (atomically).
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from torchcal.compensate.export import export_model
from torchcal.compensate.program import compensate_program
from torchcal.compensate.runtime import CompensatorRuntime
from torchcal.config.schema import FitConfig
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit, save_fit


def _program(path: Path, q: torch.Tensor) -> None:
    header = ",".join(f"q{j}" for j in range(1, q.shape[1] + 1))
    rows = [",".join(repr(v) for v in row) for row in torch.rad2deg(q).tolist()]
    path.write_text(header + "\n" + "\n".join(rows) + "\n")


def bench(n_targets: int, repeats: int, folder: Path) -> dict:
    twin = Twin.create(TwinConfig(seed=3))
    train = twin.sample(150, torch.Generator().manual_seed(11))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = fit(twin.robot, train, FitConfig(residual="none", progress=False))
    model = save_fit(folder / "model", twin.robot, train, result, {})
    q = twin.robot.sample_joints(n_targets, torch.Generator().manual_seed(5), margin=math.radians(5))
    _program(folder / "program.csv", q)
    command, solve = [], []
    outcome = None
    for _ in range(repeats):
        start = time.perf_counter()
        outcome = compensate_program(model, folder / "program.csv", folder / "corrected.csv")
        command.append(time.perf_counter() - start)
        solve.append(outcome.seconds)
    assert outcome is not None
    export_model(model, folder / "exported", allow_large_corrections=True)
    runtime = CompensatorRuntime(folder / "exported", threads=None)
    onnx = []
    for _ in range(repeats):
        start = time.perf_counter()
        q_onnx, residual = runtime.correct_with_residual(q.numpy())
        onnx.append(time.perf_counter() - start)
    written = np.loadtxt(folder / "corrected.csv", delimiter=",", skiprows=1)
    q_cmd = np.radians(written[:, : q.shape[1]])
    ok = written[:, q.shape[1]] == 1
    return {
        "n_targets": n_targets,
        "repeats": repeats,
        "model": "default twin (seed 3, geometric errors only), 150 poses, default fit with residual=none",
        "tcp": outcome.tcp_note,
        "compensate_command_s_median": statistics.median(command),
        "compensate_solve_s_median": statistics.median(solve),
        "onnxruntime_float64_s_median": statistics.median(onnx),
        "n_corrected": outcome.n_corrected,
        "largest_correction_deg": outcome.largest_correction_deg,
        "largest_correction_joint": outcome.largest_correction_joint,
        "median_correction_deg": float(np.median(np.degrees(np.abs(q_cmd - q.numpy()).max(1)))),
        "largest_difference_to_onnx_deg": float(np.degrees(np.abs(q_cmd[ok] - q_onnx[ok]).max())),
        "onnx_within_1um": int((residual[:, 0] <= 1e-6).sum()),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs, torch {torch.__version__}",
    }


def markdown(r: dict) -> str:
    return "\n".join([
        "# `torchcal compensate` on a robot program",
        "",
        f"Measured by `scripts/bench_compensate_program.py` ({r['machine']}); {r['model']}; "
        f"{r['n_targets']} joint targets uniform within the joint limits (5 deg margin); median of {r['repeats']} runs. "
        f"{r['tcp']}.",
        "",
        "| what | time, s |",
        "|---|---|",
        f"| `torchcal compensate` whole command (read, refusal check, solve, write CSV + sidecar) | {r['compensate_command_s_median']:.3f} |",
        f"| of which the compensator's solve (torch, float64) | {r['compensate_solve_s_median']:.3f} |",
        f"| the exported ONNX compensator, onnxruntime float64, all cores, one batch | {r['onnxruntime_float64_s_median']:.3f} |",
        "",
        f"Corrected: {r['n_corrected']} of {r['n_targets']} (model's TCP within 1 um of the target; onnxruntime: "
        f"{r['onnx_within_1um']}). Largest joint correction {r['largest_correction_deg']:.4g} deg (joint "
        f"{r['largest_correction_joint']}), median of each target's largest {r['median_correction_deg']:.4g} deg. "
        f"Largest difference between the written commands and onnxruntime's: {r['largest_difference_to_onnx_deg']:.2e} deg.",
        "",
    ])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/bench_compensate_program")
    parser.add_argument("--targets", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        report = bench(args.targets, args.repeats, Path(tmp))
    atomic_write_json(Path(args.out).with_suffix(".json"), report)
    atomic_write_text(Path(args.out).with_suffix(".md"), markdown(report))
    print(markdown(report))


if __name__ == "__main__":
    main()
