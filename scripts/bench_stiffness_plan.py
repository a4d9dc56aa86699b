"""Random loading against the A-optimal loading plan, through the command line, on the twin.

For each seed and each ``plan`` (``random``, ``optimal``): simulate (120 loaded training poses,
200 randomly loaded test poses), fit, evaluate, export and compensate as in
``bench_stiffness_cli.py``. Then the floor of joint 6's sigma: the stiffest springs of the
prior ranges (joint 6 at 5e4 N m/rad), planned, fitted, on a few seeds. Writes
``docs/stiffness_plan.json`` and ``docs/stiffness_plan.md``.

    python scripts/bench_stiffness_plan.py [--seeds 0 1 ... 11]
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path

from bench_stiffness_cli import one_seed

from torchcal.cli import main
from torchcal.core.io import atomic_write_text
from torchcal.instruments.stiffness.twin import MAIN_AXIS_RANGE_NM_PER_RAD, WRIST_RANGE_NM_PER_RAD

DOCS = Path(__file__).resolve().parents[1] / "docs"
BOUND = 0.10


def stiff_end(seed: int, root: Path) -> dict:
    """Joint 6's reported and predicted sigma with every spring at the stiff end of its range."""
    k = [MAIN_AXIS_RANGE_NM_PER_RAD[1]] * 3 + [WRIST_RANGE_NM_PER_RAD[1]] * 3
    case, model = root / "case", root / "model"
    main(["simulate", "instrument=stiffness", "--out", str(case), f"seed={seed}", "n_train=120", "n_test=10", f"joint_stiffness_nm_per_rad={k}"])
    main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "stiffness_train.csv"), "--out", str(model)])
    truth = json.loads((case / "stiffness_truth.json").read_text())
    p6 = json.loads((model / "stiffness.json").read_text())["parameters"]["k_j6_rz"]
    return {
        "seed": seed,
        "k_j6_rz": k[5],
        "reported_relative_std": p6["relative_std"],
        "relative_error": p6["value"] / k[5] - 1,
        "predicted_relative_std_at_truth": truth["loading_plan"]["predicted_relative_std_at_truth"]["k_j6_rz"],
    }


def summarize(rows: list[dict]) -> dict:
    """The acceptance numbers over seeds of one plan."""
    worst = [r["max_abs_rel_error_identified"] for r in rows]
    sigma6 = [r["reported_relative_std"]["k_j6_rz"] for r in rows]
    deflection = [r["deflection_rms_mm"] / r["deflection_measured_rms_mm"] for r in rows]
    removed = [1 - r["loaded_position_rms_mm"]["float64"] / r["loaded_position_rms_mm"]["before"] for r in rows]
    j6 = [abs(r["relative_errors"].get("k_j6_rz", math.nan)) for r in rows]
    return {
        "seeds": [r["seed"] for r in rows],
        "seeds_over_10_percent": [r["seed"] for r in rows if r["max_abs_rel_error_identified"] > BOUND],
        "worst_identified_rel_error": max(worst),
        "worst_k_j6_rz_rel_error": max(j6),
        "k_j6_rz_reported_sigma_range": [min(sigma6), max(sigma6)],
        "k_j6_rz_identified_on_all_seeds": all(r["status"].get("k_j6_rz") == "identified" for r in rows),
        "deflection_error_percent_of_measured_range": [100 * min(deflection), 100 * max(deflection)],
        "loaded_tcp_error_removed_percent_range": [100 * min(removed), 100 * max(removed)],
    }


def markdown(result: dict) -> str:
    s = result["summary"]
    lines = [
        "# Loading plan: random against A-optimal loading (measured)",
        "",
        "`python scripts/bench_stiffness_plan.py` writes this file and `docs/stiffness_plan.json`.",
        f"Twin seeds {s['random']['seeds'][0]}..{s['random']['seeds'][-1]}, 120 loaded training poses, 200 randomly",
        "loaded test poses, 0.012 mm tracker and 0.01 deg probe noise; `simulate`, `fit`, `evaluate`,",
        "`export` and the exported compensator (float64) as in `bench_stiffness_cli.py`.",
        "",
        "| plan | seeds over 10 % | worst stiffness error (all joints) | worst `k_j6_rz` error | `k_j6_rz` reported sigma | deflection error (% of measured RMS) | loaded TCP error removed |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for plan in ("random", "optimal"):
        r = s[plan]
        over = ", ".join(str(x) for x in r["seeds_over_10_percent"]) or "none"
        lines.append(
            f"| {plan} | {len(r['seeds_over_10_percent'])} ({over}) | {100 * r['worst_identified_rel_error']:.1f} % | "
            f"{100 * r['worst_k_j6_rz_rel_error']:.1f} % | {100 * r['k_j6_rz_reported_sigma_range'][0]:.1f}-"
            f"{100 * r['k_j6_rz_reported_sigma_range'][1]:.1f} % | {r['deflection_error_percent_of_measured_range'][0]:.1f}-"
            f"{r['deflection_error_percent_of_measured_range'][1]:.1f} % | {r['loaded_tcp_error_removed_percent_range'][0]:.1f}-"
            f"{r['loaded_tcp_error_removed_percent_range'][1]:.1f} % |"
        )
    lines += ["", "Per seed, largest relative error of an identified stiffness (`k_j6_rz` error, reported sigma):", ""]
    lines += ["| seed | random | optimal |", "| --- | --- | --- |"]
    by_seed = {(r["plan"], r["seed"]): r for r in result["runs"]}
    for seed in s["random"]["seeds"]:
        cells = []
        for plan in ("random", "optimal"):
            r = by_seed[(plan, seed)]
            cells.append(
                f"{100 * r['max_abs_rel_error_identified']:.1f} % ({100 * abs(r['relative_errors']['k_j6_rz']):.1f} %, "
                f"{100 * r['reported_relative_std']['k_j6_rz']:.1f} %)"
            )
        lines.append(f"| {seed} | {cells[0]} | {cells[1]} |")
    floor = result["stiff_end"]
    lines += [
        "",
        f"Floor of joint 6: every spring at the stiff end of its range (`k_j6_rz` = {floor[0]['k_j6_rz']:.0f} N m/rad),",
        "30 N m, 120 planned poses, 0.01 deg probe noise:",
        "",
        "| seed | `k_j6_rz` predicted sigma (plan, at truth) | reported sigma (fit) | error |",
        "| --- | --- | --- | --- |",
    ]
    for r in floor:
        lines.append(
            f"| {r['seed']} | {100 * r['predicted_relative_std_at_truth']:.2f} % | {100 * r['reported_relative_std']:.2f} % | "
            f"{100 * r['relative_error']:+.2f} % |"
        )
    return "\n".join(lines) + "\n"


def main_bench() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(12)))
    parser.add_argument("--floor-seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    runs: list[dict] = []
    for seed in args.seeds:
        for plan in ("random", "optimal"):
            with tempfile.TemporaryDirectory() as tmp:
                runs.append(one_seed(seed, Path(tmp), plan))
            print(f"seed {seed} {plan}: worst {100 * runs[-1]['max_abs_rel_error_identified']:.1f} %", flush=True)
    floor = []
    for seed in args.floor_seeds:
        with tempfile.TemporaryDirectory() as tmp:
            floor.append(stiff_end(seed, Path(tmp)))
    result = {
        "summary": {plan: summarize([r for r in runs if r["plan"] == plan]) for plan in ("random", "optimal")},
        "stiff_end": floor,
        "runs": runs,
    }
    atomic_write_text(DOCS / "stiffness_plan.json", json.dumps(result, indent=2) + "\n")
    text = markdown(result)
    atomic_write_text(DOCS / "stiffness_plan.md", text)
    print(text)


if __name__ == "__main__":
    main_bench()
