"""Does a position-only calibration know the tool's orientation? ``python scripts/orientation_real.py --data-root ../shared/data/real``.

The UR10 series were also measured with the T-Mac's orientation (the ``*_6d.csv`` files). Each fit
here sees positions only (series B or C, geometry alone and the default structure, no head); every
other series' 6-D file then scores the flange orientation the fit claims, with the tracker frame
re-fitted to that file's positions (``evaluate --register``) and the probe's rotation on the flange
fitted to its orientations, for the model and the nominal robot alike
(:mod:`torchcal.stages.orientation`). This is the orientation a compensator turns the tool by: if
the model's is closer to the measured one than the nominal robot's, correcting the orientation with
a position-only model helps; if not, the correction would claim what the data did not see.

Series A (11,911 grid rows) is scored on every 4th row. Writes ``<out>.json`` and ``<out>.md``.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
import warnings
from pathlib import Path

from torchcal.app.validation import UR10
from torchcal.config.schema import FitConfig
from torchcal.core.errors import IdentifiabilityWarning
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.data.measurements import load_measurements
from torchcal.instruments.tracker.evaluate import score
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.robot import load_robot
from torchcal.stages.geometry import predict_positions
from torchcal.stages.orientation import angles_to_measured
from torchcal.stages.pipeline import fit_model
from torchcal.stages.store import load_model

FITTED = {"B": "poses_B_joint.csv", "C": "poses_C_random.csv"}
SCORED = {"A": "poses_A_grid_6d.csv", "B": "poses_B_joint_6d.csv", "C": "poses_C_random_6d.csv", "D": "poses_D_iso_6d.csv"}
STRUCTURES = {"geometry": FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none", progress=False),
              "default (no head)": FitConfig(residual="none", progress=False)}
EVERY_A = 4


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data-root", default="../shared/data/real")
    parser.add_argument("--out", default="docs/orientation_real")
    args = parser.parse_args()
    folder = Path(args.data_root) / UR10
    robot = load_robot(folder / "robot.yaml")
    scored = {k: load_measurements(folder / f, robot) for k, f in SCORED.items()}
    scored["A"] = scored["A"].subset(list(range(0, len(scored["A"]), EVERY_A)))
    rows = []
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        for fit_name, fit_file in FITTED.items():
            data = load_measurements(folder / fit_file, robot)
            for structure, config in STRUCTURES.items():
                start = time.perf_counter()
                target = Path(tmp) / f"{fit_name}-{structure.split()[0]}"
                fit_model(target, robot, data, config)
                stored = load_model(target)
                for name, file in scored.items():
                    if name == fit_name:
                        continue
                    metrics = score(stored, file, register=True, leakage=False).metrics
                    o = metrics["orientation"]
                    rows.append({"fitted": fit_name, "structure": structure, "scored": name, "n_poses": metrics["n_poses"],
                                 "position_rms_mm": metrics["position_rms_mm"],
                                 "nominal_position_rms_mm": metrics["nominal_position_rms_mm"],
                                 "orientation_rms_deg": o["orientation_rms_deg"],
                                 "nominal_orientation_rms_deg": o["nominal"]["orientation_rms_deg"],
                                 "orientation_p95_deg": o["orientation_p95_deg"],
                                 "nominal_orientation_p95_deg": o["nominal"]["orientation_p95_deg"],
                                 "chain_only_orientation_rms_deg": _chain_only_rms_deg(stored, file),
                                 "protocol": o["protocol"], "nominal_protocol": o["nominal"]["protocol"]})
                    print(f"{fit_name} {structure:>18} -> {name}: orientation {o['orientation_rms_deg']:.4f} deg "
                          f"(nominal {o['nominal']['orientation_rms_deg']:.4f}); position {metrics['position_rms_mm']:.4f} mm "
                          f"(nominal {metrics['nominal_position_rms_mm']:.4f}); {time.perf_counter() - start:.1f} s", flush=True)
    out = Path(args.out)
    atomic_write_json(out.with_suffix(".json"), {"rows": rows, "every_a": EVERY_A})
    atomic_write_text(out.with_suffix(".md"), _table(rows))


def _chain_only_rms_deg(stored, data) -> float:
    """The model's orientation RMS (deg) with its joint-space terms left out of the orientation (the
    alternative a compensator could orient by: the calibrated geometry at the commanded joints)."""
    frame = tf.rigid_registration(predict_positions(stored, data.q), data.position) @ stored.model.instrument_from_base(stored.x)
    predicted = frame[:3, :3] @ stored.model.base_flange_pose(data.q, stored.x)[..., :3, :3]
    angles = angles_to_measured(predicted, data.rotation, fit_probe=True)
    return math.degrees(float(angles.pow(2).mean().sqrt()))


def _table(rows: list[dict]) -> str:
    lines = [
        "# Orientation of a position-only calibration on the UR10's 6-D series",
        "",
        "Written by `python scripts/orientation_real.py --data-root ../shared/data/real`. Each model was fitted to one",
        "series' positions only; each other series' 6-D file scores the flange orientation it claims. Protocol of every",
        f"orientation figure: {rows[0]['protocol']}; the nominal robot: {rows[0]['nominal_protocol']}. Positions: tracker",
        f"frame re-fitted likewise; the nominal robot with frame and tool fitted. Series A: every {EVERY_A}th row.",
        "",
        "| fitted (positions) | structure | scored | poses | orientation RMS [deg] model / nominal | ratio | "
        "p95 [deg] model / nominal | position RMS [mm] model / nominal | orientation RMS [deg], chain without joint-space terms |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['fitted']} | {r['structure']} | {r['scored']} | {r['n_poses']} | "
                     f"{r['orientation_rms_deg']:.4f} / {r['nominal_orientation_rms_deg']:.4f} | "
                     f"{r['orientation_rms_deg'] / r['nominal_orientation_rms_deg']:.2f} | "
                     f"{r['orientation_p95_deg']:.4f} / {r['nominal_orientation_p95_deg']:.4f} | "
                     f"{r['position_rms_mm']:.4f} / {r['nominal_position_rms_mm']:.4f} | "
                     f"{r['chain_only_orientation_rms_deg']:.4f} |")
    worst = max(r["orientation_rms_deg"] / r["nominal_orientation_rms_deg"] for r in rows)
    lines += ["", f"Largest ratio of the model's orientation RMS to the nominal robot's: {worst:.2f}. The last column",
              "scores the same models' orientation with their joint-space terms left out (the calibrated geometry at the",
              "commanded joints; the same as the model's for geometry alone).", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
