"""``torchcal update`` on the UR10 (ipa-ur10-tmac): an old model, 20 poses of a later series, the rest of it scored.

Cases (SOURCE.txt: A and D each have their own tracker placement, D another probe mounting; B and C
share one tracker frame):

* ``A -> D``: default fit on 3000 seeded rows of series A (numpy ``default_rng(0)`` permutation, file
  order; the rows of ``scripts/bench_fit.py``), ``update`` with 20 seeded rows of D
  (``default_rng(0)`` permutation of D's rows, the first 20), scored on the other 612 rows of D;
* ``C -> B``: default fit on all of series C, ``update`` with 20 seeded rows of B, scored on the
  other 1475 rows.

Each old model is fitted once with ``torchcal fit`` (kept in ``--work`` and reused when its folder
is there), each update runs ``torchcal update`` in a fresh process. Scored, on the rows the update
did not see:

* ``updated, own frame``: the updated model as it is (its frame from the 20 poses): what a user gets;
* ``old, frame from the 20``: the old model as it is, its frame registered (Kabsch) on the same 20
  poses: the like-for-like baseline of ``updated, own frame`` (the update with nothing freed or dropped);
* ``updated, re-registered`` / ``old, re-registered``: the frame re-fitted to the scored rows
  (Kabsch), the protocol of docs/validation.md's transfer rows (geometry alone A -> D 0.485 mm,
  default 0.675 mm);
* the share of scored rows inside the updated model's predicted 95 % region (own frame).

    python scripts/validate_update.py [--data-root ../shared/data/real] [--work DIR] [--free auto,tool]

Writes docs/validate_update.md and docs/validate_update.json.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.data.measurements import load_measurements
from torchcal.kinematics.transforms import rigid_registration
from torchcal.stages.geometry import held_out_errors, predict_positions
from torchcal.stages.prediction_uncertainty import stored_prediction
from torchcal.stages.store import load_model

SET = "ipa-ur10-tmac"
CASES = {
    "A -> D": ("poses_A_grid.csv", 3000, "poses_D_iso.csv"),
    "C -> B": ("poses_C_random.csv", None, "poses_B_joint.csv"),
}


def _rows(path: Path, count: int | None, seed: int = 0) -> tuple[str, list[str], np.ndarray]:
    lines = path.read_text().splitlines()
    order = np.random.default_rng(seed).permutation(len(lines) - 1)
    return lines[0], lines[1:], order if count is None else order[:count]


def _write(path: Path, header: str, rows: list[str], index: np.ndarray) -> Path:
    path.write_text("\n".join([header] + [rows[i] for i in np.sort(index)]) + "\n")
    return path


def _torchcal(*args: str) -> float:
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "torchcal.cli", *args], check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - started


def _rms(errors: torch.Tensor) -> float:
    return float(errors.norm(dim=-1).pow(2).mean().sqrt()) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-root", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))
    parser.add_argument("--work", default="/tmp/torchcal-validate-update")
    parser.add_argument("--free", default="auto", help="comma list of free= values to run (default: auto)")
    parser.add_argument("--few", type=int, default=20)
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs"))
    args = parser.parse_args()
    root, work = Path(args.data_root) / SET, Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    robot = root / "robot.yaml"
    results = []
    for case, (train_file, count, target_file) in CASES.items():
        tag = case.replace(" -> ", "")
        header, rows, index = _rows(root / train_file, count)
        train = _write(work / f"{tag}_train.csv", header, rows, index)
        old = work / f"{tag}_old"
        fit_s = None
        if not (old / "calibration.json").is_file():
            fit_s = _torchcal("fit", "--robot", str(robot), "--data", str(train), "--out", str(old), "progress=false")
        header, rows, order = _rows(root / target_file, None)
        few = _write(work / f"{tag}_few.csv", header, rows, order[: args.few])
        rest = _write(work / f"{tag}_rest.csv", header, rows, order[args.few :])
        stored_old = load_model(old)
        scored = load_measurements(rest, stored_old.robot)
        old_rms = _rms(held_out_errors(stored_old, scored, register=True))
        few_data = load_measurements(few, stored_old.robot)
        # the old model's predictions carry its own frame (A's); one rigid map onto the 20 poses' frame
        frame = rigid_registration(predict_positions(stored_old, few_data.q), few_data.position)
        predicted = predict_positions(stored_old, scored.q)
        old_few_rms = _rms(scored.position - (predicted @ frame[:3, :3].T + frame[:3, 3]))
        for free in args.free.split(","):
            new = work / f"{tag}_update_{free.replace(',', '_')}"
            update_s = _torchcal("update", "--model", str(old), "--data", str(few), "--out", str(new), f"free={free}")
            stored = load_model(new)
            own = held_out_errors(stored, scored)
            prediction = stored_prediction(stored, scored.q)
            inside = float("nan") if prediction is None else float(
                (own.norm(dim=-1) * 1e3 <= prediction.p95_mm).double().mean())
            update = stored.metadata["update"]
            results.append({
                "case": case, "free": free, "train": f"{train_file} ({len(stored_old.training_q) if stored_old.training_q is not None else '?'} rows)",
                "few": args.few, "scored": len(scored), "freed": update["freed"], "freed_by": update["freed_by"],
                "updated_own_frame_rms_mm": _rms(own), "updated_registered_rms_mm": _rms(held_out_errors(stored, scored, register=True)),
                "old_registered_rms_mm": old_rms, "old_frame_from_few_rms_mm": old_few_rms, "inside_predicted_95": inside,
                "dropped_terms": update.get("joint_space_terms_dropped", []),
                "leave_one_out_rms_mm": update["leave_one_out_rms_mm"], "update_s": update_s, "old_fit_s": fit_s,
            })
            print(results[-1])
    lines = [f"| case | free | freed | terms dropped | scored rows | old model, frame from the {args.few} | old model, re-registered "
             f"| updated, own frame | updated, re-registered | inside predicted 95 % | LOO RMS on the {args.few} | update time |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['case']} | {r['free']} | {', '.join(r['freed']) or 'frame only'} | "
                     f"{', '.join(r['dropped_terms']) or '-'} | {r['scored']} | {r['old_frame_from_few_rms_mm']:.3f} | "
                     f"{r['old_registered_rms_mm']:.3f} | **{r['updated_own_frame_rms_mm']:.3f}** | "
                     f"{r['updated_registered_rms_mm']:.3f} | {100 * r['inside_predicted_95']:.0f} % | "
                     f"{r['leave_one_out_rms_mm']:.3f} | {r['update_s']:.0f} s |")
    text = ("# `torchcal update` on the UR10\n\nMade by `scripts/validate_update.py` (its docstring states the protocol). "
            "RMS in mm over the rows the update did not see.\n\n" + "\n".join(lines) + "\n")
    out = Path(args.out)
    atomic_write_text(out / "validate_update.md", text)
    atomic_write_json(out / "validate_update.json", {"results": results})
    print(text)


if __name__ == "__main__":
    main()
