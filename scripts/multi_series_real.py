"""Several UR10 series fitted together: ``python scripts/multi_series_real.py --data-root ../shared/data/real``.

Fits series B alone, series C alone and B and C together (:mod:`torchcal.stages.series`), with
the default ``series_frame=auto`` (which finds one frame and one tool here: B and C were measured
from one tracker placement with one probe mount, ``SOURCE.txt``) and with a frame per series, each with the
default structure gate (``FitConfig(residual="none")``, as ``scripts/joint_models_real.py``:
heads are refused on every UR10 row), and scores each model on all of series A and all of series
D, each re-registered (the tracker frame fitted on the scored series, as ``torchcal evaluate
register=true``). Writes ``docs/multi_series_real.json`` and the table ``docs/multi_series_real.md``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import warnings
from dataclasses import replace
from pathlib import Path

from torchcal.app.validation import UR10, _structure_name
from torchcal.config.schema import FitConfig
from torchcal.core.errors import IdentifiabilityWarning
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.core.metrics import position_metrics
from torchcal.data.measurements import load_measurements
from torchcal.kinematics.robot import load_robot
from torchcal.stages.geometry import held_out_errors
from torchcal.stages.pipeline import fit_model
from torchcal.stages.series import fit_series, series_metadata
from torchcal.stages.store import load_model

FILES = {"A": "poses_A_grid.csv", "B": "poses_B_joint.csv", "C": "poses_C_random.csv", "D": "poses_D_iso.csv"}
#: (series, series_frame): B and C together with the default (``auto``: one frame here, their
#: nominal frames agree within 1.75 mm; SOURCE.txt: one tracker placement), and with a frame each
FITS = ((("B",), ""), (("C",), ""), (("B", "C"), "auto"), (("B", "C"), "per_series"))
SCORED = ("A", "D")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data-root", default="../shared/data/real")
    parser.add_argument("--out", default="docs/multi_series_real")
    args = parser.parse_args()
    folder = Path(args.data_root) / UR10
    robot = load_robot(folder / "robot.yaml")
    data = {k: load_measurements(folder / f, robot) for k, f in FILES.items()}
    config = FitConfig(residual="none", progress=False)
    rows = []
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        for names, frame in FITS:
            start = time.perf_counter()
            target = Path(tmp) / ("".join(names) + frame)
            extra: dict = {}
            if len(names) == 1:
                run = fit_model(target, robot, data[names[0]], config)
            else:
                series = [data[n] for n in names]
                fitted = fit_series(robot, series, replace(config, series_frame=frame))
                extra = {**series_metadata(series, fitted)["series"],
                         "notes": [n for n in fitted.result.notes if "series" in n or "set-ups" in n]}
                run = fit_model(target, robot, fitted.pooled, config, fitted=(fitted.result, fitted.structure))
            seconds = time.perf_counter() - start
            stored = load_model(target)
            scores = {k: position_metrics(held_out_errors(stored, data[k], register=True)) for k in SCORED}
            row = {"fit": "+".join(names) + (f" (series_frame={frame})" if frame else ""), "poses": sum(len(data[n]) for n in names), "chosen": _structure_name(run.result),
                   "structure_note": next((n for n in run.result.notes if n.startswith("structure chosen")), ""),
                   "seconds": seconds, "scores": scores, "series": extra}
            print(row["fit"], row["chosen"], {k: round(v["position_rms_mm"], 4) for k, v in scores.items()},
                  f"{seconds:.0f} s", flush=True)
            rows.append(row)
    atomic_write_json(Path(args.out + ".json"), rows)
    lines = ["| fit on | poses | structure chosen (grouped CV) | A: RMS / p95 [mm] | D: RMS / p95 [mm] | fit time [s] |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        a, d = r["scores"]["A"], r["scores"]["D"]
        lines.append(f"| {r['fit'].replace('+', ' + ')} | {r['poses']} | {r['chosen']} | "
                     f"{a['position_rms_mm']:.4f} / {a['position_p95_mm']:.4f} | "
                     f"{d['position_rms_mm']:.4f} / {d['position_p95_mm']:.4f} | {r['seconds']:.0f} |")
    atomic_write_text(Path(args.out + ".md"), "\n".join(lines) + "\n\n(written by `python scripts/multi_series_real.py`; "
                      "A and D scored whole, each re-registered: tracker frame fitted on the scored series)\n")
    print(json.dumps([r["fit"] for r in rows]))


if __name__ == "__main__":
    main()
