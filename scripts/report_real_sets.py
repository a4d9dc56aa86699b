"""Fit every public real-robot set the tracker reads and write its reports (fit, and evaluate where a series is held out).

    python scripts/report_real_sets.py [--real ../shared/data/real] [--out /tmp/torchcal-real-reports] [--only NAME]

Each set is fitted with ``torchcal fit``'s defaults (structure and residual head chosen by grouped
cross-validation); where the set has a series measured apart from the fitted one, ``evaluate
--report`` scores the model on it (``--register`` where the tracker stood elsewhere). The data are
read in place; the reports go to ``--out`` (never into the repository). Prints one line per fit and
writes ``summary.json`` there.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

#: (set, fitted file, held-out file or None, --register for the held-out file, why)
PLAN = [
    ("icelinker-irb120-faro", "poses.csv", None, False, "SMR 1; the other SMRs are other tool points"),
    ("ipa-ur10-tmac", "poses_C_random.csv", "poses_B_joint.csv", True, "B and C: two tracker frames"),
    ("ipa-ur10-tmac", "poses_D_iso.csv", None, False, "ISO 9283 cube poses, visited repeatedly; another mounting"),
    ("jacobi-ur5-gts3800", "poses.csv", "poses_test.csv", False, "the source's split"),
    ("jacobi-wam-gts3800", "poses_7dof.csv", "poses_7dof_test.csv", False, "the source's split"),
    ("lmpytorch-rokae285-50", "poses.csv", None, False, "50 poses"),
    ("lmpytorch-rokae380-30", "poses.csv", None, False, "30 poses"),
    ("lmpytorch-rokae487-30", "poses.csv", None, False, "30 poses"),
]


def _tracker_sets(real: Path) -> dict[str, str]:
    """Every folder with a tracker-readable file, and why it cannot be fitted where it cannot."""
    from torchcal.core.errors import TorchcalError
    from torchcal.instruments.registry import recognise

    found = {}
    for folder in sorted(p for p in real.iterdir() if p.is_dir()):
        readable = []
        for path in sorted(folder.glob("*.csv")):
            try:
                if recognise(path).name == "tracker":
                    readable.append(path.name)
            except TorchcalError:
                continue
        if readable:
            found[folder.name] = "" if (folder / "robot.yaml").is_file() else "no robot.yaml (the source names no robot model)"
    return found


def main() -> None:
    from torchcal.core.metrics import position_metrics
    from torchcal.instruments.base import (
        EvaluateRequest,
        FitRequest,
        evaluate_reported,
        fit_committed,
    )
    from torchcal.instruments.registry import recognise

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))
    parser.add_argument("--out", default="/tmp/torchcal-real-reports")
    parser.add_argument("--only", default=None, help="fit only this set")
    args = parser.parse_args()
    real, out = Path(args.real), Path(args.out)
    warnings.simplefilter("ignore")
    sets = _tracker_sets(real)
    planned = {name for name, *_ in PLAN}
    rows = []
    for name, reason in sets.items():
        if name not in planned:
            rows.append({"set": name, "skipped": reason or "tracker-readable but not in PLAN"})
            print(f"{name}: skipped ({rows[-1]['skipped']})")
    for name, fit_file, test_file, register, why in PLAN:
        if args.only and name != args.only:
            continue
        folder = real / name
        model = out / name / Path(fit_file).stem / "model"
        started = time.perf_counter()
        outcome = fit_committed(recognise(folder / fit_file), FitRequest(
            robot=folder / "robot.yaml", data=folder / fit_file, out=model, overrides=["progress=false"]))
        seconds = time.perf_counter() - started
        meta = json.loads((model / "calibration.json").read_text())
        selection = json.loads((model / "model_selection.json").read_text())
        chosen = next(r for r in selection["candidates"] if r["name"] == selection["chosen"])
        row = {"set": name, "fit": fit_file, "why": why, "poses": meta["data"]["n_poses"], "fit_s": round(seconds, 1),
               "nominal_training_rms_mm": meta["fit_metrics"]["nominal"]["position_rms_mm"],
               "geometry_stage_training_rms_mm": meta["fit_metrics"]["geometry_stage"]["position_rms_mm"],
               "chosen": selection["chosen"], "cv_rms_mm": chosen["cv_rms_mm"], "model": outcome.lines[-1],
               "report": str(model / "report.html")}
        if test_file is not None:
            evaluation = out / name / Path(fit_file).stem / f"evaluate_{Path(test_file).stem}"
            result = evaluate_reported(recognise(folder / test_file), EvaluateRequest(
                model=model, data=folder / test_file, register=register, report=evaluation))
            row.update({"held_out": test_file, "registered": register, "held_out_poses": result.metrics["n_poses"],
                        "held_out_rms_mm": result.metrics["position_rms_mm"],
                        "iso9283_repeated_poses": result.metrics["iso9283"]["repeated_poses"],
                        "evaluation_report": str(evaluation / "report.html")})
        else:
            from torchcal.data.measurements import load_measurements
            from torchcal.stages.geometry import held_out_errors
            from torchcal.stages.store import load_model

            stored = load_model(model)
            data = load_measurements(folder / fit_file, stored.robot)
            row["training_rms_mm"] = position_metrics(held_out_errors(stored, data))["position_rms_mm"]
        for path in (model / "report.md", model / "report.html"):
            assert path.is_file(), path
        rows.append(row)
        held = f", held-out {row['held_out_rms_mm']:.4f} mm on {test_file}" if test_file else ""
        print(f"{name}/{fit_file}: {row['poses']} poses, {seconds:.0f} s; nominal {row['nominal_training_rms_mm']:.4f} mm, "
              f"{row['chosen']} CV {row['cv_rms_mm']:.4f} mm{held}; {row['report']}", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
