"""Stiffness through the command line and the exported compensator, on the loading-rig twin.

For each seed: ``torchcal simulate instrument=stiffness`` (120 training, 200 test poses; the
default ``plan=optimal`` loading, or ``--plan random``),
``torchcal fit``, ``torchcal evaluate``, ``torchcal export``; then the exported compensator
(onnxruntime runner, float64 and float32) corrects 300 regular poses under random wrenches and
the true loaded robot (exact deformed chain) is measured against the target. Prints a Markdown
table and writes ``docs/stiffness_cli.json``.

    python scripts/bench_stiffness_cli.py [--seeds 0 1 2] [--plan optimal|random]
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path

import torch

from torchcal.cli import main
from torchcal.compensate.runtime import CompensatorRuntime
from torchcal.core.io import atomic_write_text
from torchcal.instruments.stiffness.twin import StiffnessTwin
from torchcal.instruments.stiffness.twin_case import StiffnessCaseConfig


def one_seed(seed: int, root: Path, plan: str = "optimal") -> dict:
    """Simulate, fit, evaluate, export and compensate one twin seed under the loading ``plan``."""
    case, model, exported = root / "case", root / "model", root / "exported"
    main(["simulate", "instrument=stiffness", "--out", str(case), f"seed={seed}", "n_train=120", "n_test=200", f"plan={plan}"])
    main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "stiffness_train.csv"), "--out", str(model)])
    main(["evaluate", "--model", str(model), "--data", str(case / "stiffness_test.csv"), "--json", str(root / "e.json")])
    main(["export", "--model", str(model), "--out", str(exported)])
    truth = json.loads((case / "stiffness_truth.json").read_text())["joint_stiffness_nm_per_rad"]
    meta = json.loads((model / "stiffness.json").read_text())
    rel = {n: p["value"] / truth[n] - 1 for n, p in meta["parameters"].items() if p["status"] == "identified"}
    metrics = json.loads((root / "e.json").read_text())

    twin = StiffnessTwin(StiffnessCaseConfig(seed=seed).twin_config())
    gen = torch.Generator().manual_seed(1000 + seed)
    q = twin.sample_poses(300, gen)
    wrench = twin.sample_wrenches(300, gen)
    target = twin.unloaded_pose(q)

    def errors(qq: torch.Tensor) -> tuple[float, float]:
        loaded = twin.loaded_pose(qq, wrench)
        dp = (loaded[:, :3, 3] - target[:, :3, 3]).norm(dim=-1) * 1e3
        rot = loaded[:, :3, :3] @ target[:, :3, :3].transpose(-1, -2)
        angle = torch.acos(((rot.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))
        return float(dp.pow(2).mean().sqrt()), math.degrees(float(angle.pow(2).mean().sqrt()))

    before = errors(q)
    after = {}
    for precision in ("float64", "float32"):
        rt = CompensatorRuntime(exported, precision=precision)
        after[precision] = errors(torch.from_numpy(rt.correct(q.numpy(), wrench.numpy())).double())
    manifest = json.loads((exported / "manifest.json").read_text())
    return {
        "seed": seed,
        "plan": plan,
        "max_abs_rel_error_identified": max(abs(v) for v in rel.values()),
        "relative_errors": rel,
        "reported_relative_std": {n: p["relative_std"] for n, p in meta["parameters"].items()},
        "status": {n: p["status"] for n, p in meta["parameters"].items()},
        "unobservable": meta["unobservable"],
        "deflection_rms_mm": metrics["deflection_rms_mm"],
        "deflection_measured_rms_mm": metrics["deflection_measured_rms_mm"],
        "loaded_position_rms_mm": {"before": before[0], **{k: v[0] for k, v in after.items()}},
        "loaded_rotation_rms_deg": {"before": before[1], **{k: v[1] for k, v in after.items()}},
        "float32_budget_compensator_tcp_max_mm": manifest["float32_error_budget"]["compensator_tcp_mm"]["max"],
    }


def main_bench() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--plan", choices=("optimal", "random"), default="optimal")
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "stiffness_cli.json"))
    args = parser.parse_args()
    rows = []
    for seed in args.seeds:
        with tempfile.TemporaryDirectory() as tmp:
            rows.append(one_seed(seed, Path(tmp), args.plan))
    atomic_write_text(args.out, json.dumps(rows, indent=2) + "\n")
    print("| seed | max rel. error (identified) | deflection RMS mm (error / measured) | loaded TCP RMS mm: before -> f64 / f32 | reduction | rotation RMS deg: before -> f64 |")
    print("| --- | --- | --- | --- | --- | --- |")
    for r in rows:
        p, a = r["loaded_position_rms_mm"], r["loaded_rotation_rms_deg"]
        print(
            f"| {r['seed']} | {100 * r['max_abs_rel_error_identified']:.1f} % | {r['deflection_rms_mm']:.4f} / "
            f"{r['deflection_measured_rms_mm']:.3f} ({100 * r['deflection_rms_mm'] / r['deflection_measured_rms_mm']:.1f} %) | "
            f"{p['before']:.3f} -> {p['float64']:.4f} / {p['float32']:.4f} | {100 * (1 - p['float64'] / p['before']):.1f} % | "
            f"{a['before']:.4f} -> {a['float64']:.5f} |"
        )


if __name__ == "__main__":
    main_bench()
