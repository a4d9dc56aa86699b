"""Does a position-only calibration know the tool's orientation? ``python scripts/orientation_real.py [--data-root ../shared/data/real]``.

Two robots measured the orientation as well as the position; every fit here sees positions only:

* **UR10** (`ipa-ur10-tmac`): the T-Mac's orientation (``*_6d.csv``). Fits on series B or C
  (geometry alone and the default structure, no head); every other series' 6-D file scores them,
  with the tracker frame re-fitted to that file's positions (``evaluate --register``). Series A
  (11,911 grid rows) is scored on every 4th row.
* **IRB 120** (`icelinker-irb120-faro`): three SMRs on the tool, 150 mm apart (their distances
  vary by 0.005 mm: the nest's orientation to about 0.003 deg). Fits on SMR 1's positions in a
  grouped 5-fold CV (whole configuration regions held out); the held-out poses' orientation is the
  nest frame of the three SMRs (origin SMR 2, x towards SMR 1, SMR 3 in the xy plane).

**Orientation table**: the flange orientation each fit claims against the measured one
(:mod:`torchcal.stages.orientation`: probe rotation on the flange fitted to the orientations, for the
model and the nominal robot alike).

**Replay table** (:mod:`torchcal.compensate.replay`): what commands leave on the robot, replayed from
the measured poses to first order, with the measured point as the TCP: no compensation, the
compensator, the same graph correcting the position only (the orientation not targeted), and the compensator's
corrections capped at 0.3 deg per joint. Poses near a singularity are left out (there any command's
wrist swing is large by the geometry). ``confirmed`` is the least-squares multiple of the
compensator's orientation change that the measured orientations call for (1: the change is what the
robot needed), over the poses whose orientation the compensator reaches in its steps. Writes
``<out>.json`` and ``<out>.md``.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
import warnings
from dataclasses import replace
from pathlib import Path

import torch

from torchcal.app.validation import UR10
from torchcal.compensate.export_checks import regular_mask
from torchcal.compensate.replay import (
    PROTOCOL,
    Replayed,
    command_sets,
    confirmed_share,
    replay,
    solved_mask,
)
from torchcal.config.schema import FitConfig
from torchcal.core.errors import IdentifiabilityWarning
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.data.folds import grouped_folds
from torchcal.data.measurements import Measurements, load_measurements
from torchcal.instruments.tracker.evaluate import score
from torchcal.kinematics.robot import load_robot
from torchcal.stages.geometry import model_joints, registered_frame
from torchcal.stages.orientation import angles_to_measured
from torchcal.stages.pipeline import fit_model
from torchcal.stages.store import load_model

IRB120 = "icelinker-irb120-faro"
FITTED = {"B": "poses_B_joint.csv", "C": "poses_C_random.csv"}
SCORED = {"A": "poses_A_grid_6d.csv", "B": "poses_B_joint_6d.csv", "C": "poses_C_random_6d.csv", "D": "poses_D_iso_6d.csv"}
STRUCTURES = {"geometry": FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none", progress=False),
              "default (no head)": FitConfig(residual="none", progress=False)}
EVERY_A = 4
CAP_DEG = 0.3
SETS = ("uncompensated", "compensator", "position only", f"capped at {CAP_DEG:g} deg")


def nest_rotation(p1: torch.Tensor, p2: torch.Tensor, p3: torch.Tensor) -> torch.Tensor:
    """``(n, 3, 3)`` orientation of the frame of three points ``(n, 3)``: origin ``p2``, x towards ``p1``, ``p3`` in xy."""
    x = torch.nn.functional.normalize(p1 - p2, dim=-1)
    z = torch.nn.functional.normalize(torch.cross(x, p3 - p2, dim=-1), dim=-1)
    return torch.stack([x, torch.cross(z, x, dim=-1), z], dim=-1)


def irb120_with_orientation(folder: Path, robot) -> Measurements:
    """SMR 1's positions with the three SMRs' nest orientation (rows of the three files are the same poses)."""
    smr = [load_measurements(folder / name, robot) for name in ("poses.csv", "poses_smr2.csv", "poses_smr3.csv")]
    if not all(torch.equal(smr[0].q, s.q) for s in smr[1:]):
        raise SystemExit(f"{folder}: the three SMR files do not list the same joints row by row")
    return replace(smr[0], rotation=nest_rotation(*(s.position for s in smr)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data-root", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))
    parser.add_argument("--out", default="docs/orientation_real")
    args = parser.parse_args()
    orientation_rows: list[dict] = []
    replay_rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        _ur10(Path(args.data_root) / UR10, Path(tmp), orientation_rows, replay_rows)
        _irb120(Path(args.data_root) / IRB120, Path(tmp), orientation_rows, replay_rows)
    out = Path(args.out)
    atomic_write_json(out.with_suffix(".json"), {"orientation": orientation_rows, "replay": replay_rows,
                                                 "every_a": EVERY_A, "cap_deg": CAP_DEG, "replay_protocol": PROTOCOL})
    atomic_write_text(out.with_suffix(".md"), _tables(orientation_rows, replay_rows))


def _ur10(folder: Path, tmp: Path, orientation_rows: list[dict], replay_rows: list[dict]) -> None:
    robot = load_robot(folder / "robot.yaml")
    scored = {k: load_measurements(folder / f, robot) for k, f in SCORED.items()}
    scored["A"] = scored["A"].subset(list(range(0, len(scored["A"]), EVERY_A)))
    for fit_name, fit_file in FITTED.items():
        data = load_measurements(folder / fit_file, robot)
        for structure, config in STRUCTURES.items():
            start = time.perf_counter()
            target = tmp / f"ur10-{fit_name}-{structure.split()[0]}"
            fit_model(target, robot, data, config)
            stored = load_model(target)
            for name, file in scored.items():
                if name == fit_name:
                    continue
                case = {"robot": "UR10", "fitted": f"series {fit_name}", "structure": structure, "scored": f"series {name}"}
                orientation_rows.append({**case, **_orientation(stored, file)})
                replay_rows.append({**case, **_replayed([(stored, file)])})
                print(f"UR10 {fit_name} {structure:>18} -> {name}: {_line(orientation_rows[-1], replay_rows[-1])}; "
                      f"{time.perf_counter() - start:.1f} s", flush=True)


def _irb120(folder: Path, tmp: Path, orientation_rows: list[dict], replay_rows: list[dict]) -> None:
    robot = load_robot(folder / "robot.yaml")
    data = irb120_with_orientation(folder, robot)
    folds = grouped_folds(robot, data.q, 5, seed=0)
    for structure, config in STRUCTURES.items():
        start = time.perf_counter()
        pairs, scores = [], []
        for k, (train, held_out) in enumerate(folds.splits()):
            target = tmp / f"irb120-{structure.split()[0]}-{k}"
            fit_model(target, robot, replace(data.subset(train), rotation=None), config)
            stored, test = load_model(target), data.subset(held_out)
            pairs.append((stored, test))
            scores.append(_orientation(stored, test))
        case = {"robot": "IRB 120", "fitted": "SMR 1, 4 of 5 grouped folds", "structure": structure,
                "scored": "held-out fold (nest of 3 SMRs)"}
        orientation_rows.append({**case, **_pooled(scores)})
        replay_rows.append({**case, **_replayed(pairs)})
        print(f"IRB 120 {structure:>18}: {_line(orientation_rows[-1], replay_rows[-1])}; "
              f"{time.perf_counter() - start:.1f} s", flush=True)


def _orientation(stored, data: Measurements) -> dict:
    """The model's and the nominal robot's orientation and position errors on ``data`` (``evaluate --register``)."""
    metrics = score(stored, data, register=True, leakage=False, corrections=False).metrics
    o = metrics["orientation"]
    return {"n_poses": metrics["n_poses"], "position_rms_mm": metrics["position_rms_mm"],
            "nominal_position_rms_mm": metrics["nominal_position_rms_mm"],
            "orientation_rms_deg": o["orientation_rms_deg"], "nominal_orientation_rms_deg": o["nominal"]["orientation_rms_deg"],
            "orientation_p95_deg": o["orientation_p95_deg"], "nominal_orientation_p95_deg": o["nominal"]["orientation_p95_deg"],
            "whole_chain_orientation_rms_deg": _whole_chain_rms_deg(stored, data),
            "protocol": o["protocol"], "nominal_protocol": o["nominal"]["protocol"]}


def _pooled(scores: list[dict]) -> dict:
    """Fold rows pooled: RMS over all held-out poses (weighted by count), p95 as the folds' largest."""
    n = sum(s["n_poses"] for s in scores)

    def rms(key: str) -> float:
        return math.sqrt(sum(s[key] ** 2 * s["n_poses"] for s in scores) / n)

    pooled = {key: rms(key) for key in ("position_rms_mm", "nominal_position_rms_mm", "orientation_rms_deg",
                                        "nominal_orientation_rms_deg", "whole_chain_orientation_rms_deg")}
    pooled.update({key: max(s[key] for s in scores) for key in ("orientation_p95_deg", "nominal_orientation_p95_deg")})
    return {"n_poses": n, **pooled, "protocol": scores[0]["protocol"], "nominal_protocol": scores[0]["nominal_protocol"]}


def _replayed(pairs: list[tuple]) -> dict:
    """Each command set replayed on the regular poses of every ``(model, scored poses)`` pair, pooled; the
    confirmed share over the poses whose orientation the compensator reaches (:func:`solved_mask`)."""
    pooled: dict[str, list] = {name: [] for name in SETS}
    solved: list[torch.Tensor] = []
    total = 0
    for stored, data in pairs:
        total += len(data)
        data = data.subset(torch.nonzero(regular_mask(stored.robot, data.q))[:, 0])
        solved.append(solved_mask(stored, data.q))
        for name, replayed in replay(stored, data, command_sets(stored, data.q, CAP_DEG)).items():
            pooled[name].append(replayed)
    out: dict = {"n_regular": sum(len(r.position_error) for r in pooled["compensator"]), "n_poses": total,
                 "n_solved": int(sum(int(m.sum()) for m in solved))}
    for name, parts in pooled.items():
        rotation = torch.cat([r.rotation_error for r in parts])
        position = torch.cat([r.position_error for r in parts])
        largest = torch.cat([r.largest_correction for r in parts])
        out[name] = {"orientation_rms_deg": math.degrees(float(rotation.norm(dim=-1).pow(2).mean().sqrt())),
                     "position_rms_mm": float(position.norm(dim=-1).pow(2).mean().sqrt()) * 1e3,
                     "share_above_cap": float((largest > math.radians(CAP_DEG) + 1e-12).double().mean()),
                     "median_joint_correction_deg": math.degrees(float(largest.median()))}
    before, after = (_solved_part(pooled[name], solved) for name in ("uncompensated", "compensator"))
    out["confirmed"] = confirmed_share(before, after)
    return out


def _solved_part(parts: list[Replayed], masks: list[torch.Tensor]) -> Replayed:
    """The pooled replay of the poses the masks keep."""
    def cat(key: str) -> torch.Tensor:
        return torch.cat([getattr(p, key)[m] for p, m in zip(parts, masks)])

    return Replayed(cat("rotation_error"), cat("position_error"), cat("largest_correction"))


def _whole_chain_rms_deg(stored, data) -> float:
    """The orientation RMS (deg) of the whole calibrated chain, joint-space terms included (what the
    compensator oriented by before it oriented position-only models by their geometry)."""
    predicted = registered_frame(stored, data)[:3, :3] @ stored.model.base_flange_pose(model_joints(stored, data.q), stored.x)[..., :3, :3]
    angles = angles_to_measured(predicted, data.rotation, fit_probe=True)
    return math.degrees(float(angles.pow(2).mean().sqrt()))


def _line(o: dict, r: dict) -> str:
    return (f"orientation {o['orientation_rms_deg']:.4f} deg (nominal {o['nominal_orientation_rms_deg']:.4f}); replayed "
            f"orientation {r['uncompensated']['orientation_rms_deg']:.4f} -> {r['compensator']['orientation_rms_deg']:.4f} "
            f"(capped {r[SETS[3]]['orientation_rms_deg']:.4f}); confirmed {r['confirmed']:.2f}")


def _tables(orientation_rows: list[dict], replay_rows: list[dict]) -> str:
    first = orientation_rows[0]
    lines = [
        "# Orientation of a position-only calibration, measured on two robots",
        "",
        "Written by `python scripts/orientation_real.py` (the public sets read in place, `--data-root`, default ../shared/data/real). Every fit saw positions only.",
        "UR10: fitted on one series, scored on each other series' 6-D file (T-Mac orientation), every "
        f"{EVERY_A}th row of series A. IRB 120: grouped 5-fold CV on SMR 1's positions; the held-out poses' orientation",
        "is the nest frame of the three SMRs on the tool (150 mm apart, their distances constant to 0.005 mm).",
        "",
        "## The orientation each fit claims",
        "",
        f"Protocol: {first['protocol']}; the nominal robot: {first['nominal_protocol']}. Positions: tracker frame",
        "re-fitted likewise; the nominal robot with frame and tool fitted.",
        "",
        "| robot | fitted (positions) | structure | scored | poses | orientation RMS [deg] model / nominal | ratio | "
        "p95 [deg] model / nominal | position RMS [mm] model / nominal | orientation RMS [deg], whole chain with its joint-space terms |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in orientation_rows:
        lines.append(f"| {r['robot']} | {r['fitted']} | {r['structure']} | {r['scored']} | {r['n_poses']} | "
                     f"{r['orientation_rms_deg']:.4f} / {r['nominal_orientation_rms_deg']:.4f} | "
                     f"{r['orientation_rms_deg'] / r['nominal_orientation_rms_deg']:.2f} | "
                     f"{r['orientation_p95_deg']:.4f} / {r['nominal_orientation_p95_deg']:.4f} | "
                     f"{r['position_rms_mm']:.4f} / {r['nominal_position_rms_mm']:.4f} | "
                     f"{r['whole_chain_orientation_rms_deg']:.4f} |")
    worst = max(r["orientation_rms_deg"] / r["nominal_orientation_rms_deg"] for r in orientation_rows)
    whole = max(r["whole_chain_orientation_rms_deg"] / r["nominal_orientation_rms_deg"] for r in orientation_rows)
    lines += ["", f"Largest ratio of the model's orientation RMS to the nominal robot's: {worst:.2f}. The model's orientation",
              "is the one its compensator acts on: a position-only fit's geometry (the MDH table at the commanded joints). The",
              "last column scores the whole chain, joint-space terms included (the same for geometry alone); its largest",
              f"ratio to the nominal robot: {whole:.2f}. IRB 120 rows pool the five held-out folds (RMS over all poses; p95:",
              "the largest fold's).", "",
              "## What the commands leave on the robot (replayed)", "",
              f"Protocol: {PROTOCOL}. Poses near a singularity left out (the export's strata). Command sets: none; the",
              "compensator (position and orientation); the same graph correcting the position only; the compensator's",
              f"corrections scaled per pose so that no joint moves more than {CAP_DEG:g} deg. `> {CAP_DEG:g} deg`: share of poses",
              "whose largest joint correction exceeds it. `confirmed`: the least-squares multiple of the compensator's",
              "orientation change that the measured orientations call for (1: what the robot needed), over the poses whose",
              "orientation the compensator reaches in its steps (`solved`; near the wrist singularity its bounded swing",
              "leaves some short).", "",
              "| robot | fitted | structure | scored | poses | orientation RMS [deg]: none / compensator / position only / "
              f"capped {CAP_DEG:g} | position RMS [mm]: none / compensator / position only / capped | compensator: "
              f"median largest correction [deg], > {CAP_DEG:g} deg | solved | confirmed |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in replay_rows:
        o = " / ".join(f"{r[s]['orientation_rms_deg']:.4f}" for s in SETS)
        p = " / ".join(f"{r[s]['position_rms_mm']:.3f}" for s in SETS)
        c = r["compensator"]
        lines.append(f"| {r['robot']} | {r['fitted']} | {r['structure']} | {r['scored']} | {r['n_regular']} of "
                     f"{r['n_poses']} | {o} | {p} | {c['median_joint_correction_deg']:.3f}, {100 * c['share_above_cap']:.0f} % | "
                     f"{r['n_solved']} | {r['confirmed']:.2f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
