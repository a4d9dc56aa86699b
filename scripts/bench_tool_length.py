"""The compensator's ``tool_length`` on true robots: where a tool beyond the TCP lands.

The position-first compensator holds the exported TCP exactly; where only the wrist can hold it
(near the elbow, shoulder or wrist singularity) it turns the tool, and a point ``d`` beyond the
TCP then misses by about ``d`` times the turn. ``export --tool-length-mm L`` keeps the nominal
command wherever the corrected one would leave a point ``L`` beyond the TCP further off (by the
model's bound ``|e_p| + L theta``). For three twin robots (gravity sag and gear errors in the
truth; a geometry-only fit on 300 poses; the exported TCP the flange), each ``L`` and poses
uniform within the joint limits and with the wrist near its singularity, this measures on the
true robot the position error of points 0, 100 and 200 mm beyond the flange along its z axis
(targets: the nominal robot's, in the calibrated instrument frame), the tool's orientation error,
and the share of poses given the nominal command.

    python scripts/bench_tool_length.py [--out docs/bench_tool_length] [--poses 2000]

Writes ``OUT.json`` and ``OUT.md`` (atomically).
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import warnings
from pathlib import Path

ROBOTS = ("twin-kr6", "twin-ur10", "twin-iiwa7")
TOOL_LENGTHS_MM = (0.0, 100.0, 200.0)
POINTS_MM = (0.0, 100.0, 200.0)


def _offset(z_m: float):
    import torch

    t = torch.eye(4, dtype=torch.float64)
    t[2, 3] = z_m
    return t


def measure_robot(robot: str, n_poses: int, tmp: Path) -> dict:
    """The table's rows of one twin robot: for each tool length, each pose set, each point."""
    import torch

    from torchcal.compensate.compensator import CompensatorGraph
    from torchcal.compensate.export_checks import wrist_singular_samples
    from torchcal.compensate.production_tcp import production_view, tcp_transform
    from torchcal.config.schema import FitConfig
    from torchcal.core.metrics import position_metrics
    from torchcal.kinematics import transforms as tf
    from torchcal.kinematics.robot import default_robot_path
    from torchcal.sim.twin import Twin, TwinConfig
    from torchcal.stages.geometry import fit, save_fit
    from torchcal.stages.store import load_model

    twin = Twin.create(TwinConfig(seed=0, robot=str(default_robot_path().with_name(f"{robot}.yaml"))))
    gen = torch.Generator().manual_seed(1)
    train = twin.sample(300, gen)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = fit(twin.robot, train, FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none",
                                                  progress=False))
        stored = production_view(load_model(save_fit(tmp / robot, twin.robot, train, result, {})), tcp_transform(None, None))
    pose_sets = {"uniform": twin.robot.sample_joints(n_poses, gen),
                 "wrist within 1 deg of singular": wrist_singular_samples(twin.robot, n_poses, gen)}
    T_cal = stored.model.instrument_from_base(stored.x)
    rows = []
    for length_mm in TOOL_LENGTHS_MM:
        graph = CompensatorGraph.from_stored(stored, tool_length=length_mm * 1e-3)
        for label, q in pose_sets.items():
            with torch.no_grad():
                q_c, _ = graph.solve(q)
                kept = (q_c == q).all(-1)
                true_flange = twin.T_instrument_base() @ twin.model.base_flange_pose(q_c + twin.joint_deviation(q_c),
                                                                                   twin.x_true)
                target_flange = T_cal @ twin.robot.flange_pose(q)
            turn = tf.so3_log(true_flange[:, :3, :3] @ target_flange[:, :3, :3].transpose(-1, -2)).norm(dim=-1)
            row = {"robot": robot, "tool_length_mm": length_mm, "poses": label, "n_poses": len(q),
                   "kept_nominal_share": float(kept.double().mean()),
                   "orientation_deg": {"rms": math.degrees(float(turn.pow(2).mean().sqrt())),
                                       "p99": math.degrees(float(turn.quantile(0.99))), "max": math.degrees(float(turn.max()))}}
            for point_mm in POINTS_MM:
                offset = _offset(point_mm * 1e-3)
                error = (true_flange @ offset)[:, :3, 3] - (target_flange @ offset)[:, :3, 3]
                row[f"point_{point_mm:g}mm"] = position_metrics(error)
            rows.append(row)
    return {"robot": robot, "rows": rows}


def markdown(report: dict) -> str:
    m = report["machine"]
    lines = ["# Where a tool beyond the TCP lands: the compensator's `tool_length`", "",
             f"Machine: {m['cpu']}, {m['cores']} cores; torch {m['torch']}. {__doc__.split('Writes')[0].split('    python')[0].strip()}",
             "", "Position errors (mm) of the true robot's points beyond the flange, RMS / p95 / max; orientation error of "
             "the true flange (deg) RMS / max:", "",
             "| robot | poses | tool_length (mm) | nominal command kept | flange | 100 mm beyond | 200 mm beyond | orientation |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for robot in report["robots"]:
        for r in robot["rows"]:
            cells = [f"{r[f'point_{p:g}mm']['position_rms_mm']:.3f} / {r[f'point_{p:g}mm']['position_p95_mm']:.3f} / "
                     f"{r[f'point_{p:g}mm']['position_max_mm']:.2f}" for p in POINTS_MM]
            lines.append(f"| {r['robot']} | {r['poses']} | {r['tool_length_mm']:g} | {100 * r['kept_nominal_share']:.1f} % | "
                         + " | ".join(cells) + f" | {r['orientation_deg']['rms']:.3f} / {r['orientation_deg']['max']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="true-robot errors of points beyond the TCP against the tool_length option")
    parser.add_argument("--out", default="docs/bench_tool_length", help="output path without extension")
    parser.add_argument("--poses", type=int, default=2000, help="poses per set (uniform, wrist near singular)")
    args = parser.parse_args(argv)

    import tempfile

    import torch
    from rich.console import Console

    from torchcal.core.io import atomic_write_json, atomic_write_text

    console = Console()
    robots = []
    with tempfile.TemporaryDirectory() as tmp_name:
        for robot in ROBOTS:
            with console.status(f"[bold]{robot}: fit, then compensate {2 * args.poses} poses for each tool length"):
                robots.append(measure_robot(robot, args.poses, Path(tmp_name)))
    report = {"machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                          "python": platform.python_version(), "torch": torch.__version__},
              "robots": robots}
    atomic_write_json(Path(args.out).with_suffix(".json"), report)
    atomic_write_text(Path(args.out).with_suffix(".md"), markdown(report))
    console.print(markdown(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
