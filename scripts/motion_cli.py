"""``torchcal motion`` through the singular neighbourhoods of the twin-kr6: the figures of docs/motion.md.

Every figure of the main table is what the command itself wrote (``motion.json`` of its report),
checked here by a second forward kinematics (a textbook MDH product in NumPy read from the robot
YAML, not torchcal's chain) on the joints of the written TRAJ.csv, and by finite differences of
those joints. Scenarios (base frame, constant tool orientation, 250 mm/s, dt = 4 ms):

* ``wrist``: 400 mm line of the nominal robot through its wrist singularity (q5 = 0 at its middle);
* ``regular``: 400 mm line far from any singularity (q5 about 60 deg at its middle);
* ``shoulder_x``, ``shoulder_xy`` (300 mm), ``shoulder_z``: lines through a shoulder singularity (the
  wrist centre on axis 1 at the middle; along ``shoulder_z`` it stays on axis 1 the whole way);
* ``elbow``: 300 mm radial line ending at the stretched elbow (q3 = -85.25 deg), and ``elbow_beyond``
  2 mm past it; ``reach``: a line out of the TCP's reach (the command refuses it);
* ``wrist_model``: the wrist line planned with ``--model`` (a twin calibrated by ``torchcal fit``):
  the real robot passes the singularity at a small distance; its path error is measured on the
  twin's true robot.

A second table compares, on the wrist line, the earlier closed-loop DLS (``torchcal.motion.follow``,
the method of scripts/motion_demo.py) with the command's position-first planning, both measured the
same way. Writes docs/motion_cli.json, the section of docs/motion.md between its markers, and
docs/img/motion_cli_*.png.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import yaml

from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import solve_ik
from torchcal.kinematics.robot import default_robot_path, load_robot
from torchcal.motion.scenario import perturbed_parameters, singular_line
from torchcal.motion.waypoints import waypoints_csv

ROOT = Path(__file__).resolve().parents[1]
DEG = math.pi / 180.0
BEGIN, END = "<!-- motion_cli:begin -->", "<!-- motion_cli:end -->"
TORCHCAL = [sys.executable, "-m", "torchcal.cli"]


def mdh_fk(q: np.ndarray) -> np.ndarray:
    """Second forward kinematics: Craig's MDH product from the YAML text, times the tool (m)."""
    doc = yaml.safe_load(default_robot_path().read_text())["kinematics"]
    out = np.broadcast_to(np.eye(4), (*q.shape[:-1], 4, 4)).copy()
    for i, j in enumerate(doc["joints"]):
        alpha, a, theta, d = math.radians(j["alpha"]), j["a"] * 1e-3, math.radians(j["theta"]), j["d"] * 1e-3
        ca, sa = math.cos(alpha), math.sin(alpha)
        ct, st = np.cos(theta + q[..., i]), np.sin(theta + q[..., i])
        link = np.zeros((*q.shape[:-1], 4, 4))
        link[..., 0, :] = np.stack([ct, -st, np.zeros_like(ct), np.full_like(ct, a)], -1)
        link[..., 1, :] = np.stack([st * ca, ct * ca, np.full_like(ct, -sa), np.full_like(ct, -sa * d)], -1)
        link[..., 2, :] = np.stack([st * sa, ct * sa, np.full_like(ct, ca), np.full_like(ct, ca * d)], -1)
        link[..., 3, 3] = 1.0
        out = out @ link
    tool = np.eye(4)
    tool[:3, 3] = np.array(doc["tool"]) * 1e-3
    return out @ tool


def segment_error_mm(points: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    u = end - start
    lam = np.clip((points - start) @ u / (u @ u), 0.0, 1.0)
    return np.linalg.norm(points - (start + lam[:, None] * u), axis=-1) * 1e3


def rates(q: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    padded = np.concatenate([q[:1], q, q[-1:]])
    return np.abs(np.diff(q, axis=0)).max(0) / dt / DEG, np.abs(np.diff(padded, 2, axis=0)).max(0) / dt**2 / DEG


def scenarios(model: ErrorModel, x: torch.Tensor) -> dict:
    """Waypoint poses (2, 4, 4) and start joints (deg) of each scenario."""
    out = {}

    def line(name: str, q_mid_deg, direction, length=0.4) -> None:
        built = singular_line(model, x, q_singular=torch.tensor(q_mid_deg, dtype=torch.float64) * DEG,
                              direction=torch.tensor(direction, dtype=torch.float64), length_m=length, spin_rad=0.0)
        out[name] = (torch.stack([built.path.start, built.path.end]), (built.q_start / DEG).tolist())

    line("wrist", [10, -80, 10, 0, 0, 20], [1, 0, 0])
    line("regular", [10, -80, 10, 0, 60, 20], [1, 0, 0])
    line("shoulder_x", [10, -80, 84.7, 0, 40, 20], [1, 0, 0])
    line("shoulder_xy", [10, -80, 84.7, 0, 40, 20], [1, 1, 0], length=0.3)
    line("shoulder_z", [10, -80, 84.7, 0, 40, 20], [0, 0, 1])
    q_elbow = torch.tensor([10, -60, -85.25, 0, 40, 20], dtype=torch.float64) * DEG
    stretched = model.tcp_pose(q_elbow, x)
    bent = q_elbow.clone()
    bent[2] += 40 * DEG
    u = stretched[:3, 3] - model.tcp_pose(bent, x)[:3, 3]
    u = u / u.norm()
    for name, beyond in (("elbow", 0.0), ("elbow_beyond", 0.002), ("reach", 0.05)):
        start, end = stretched.clone(), stretched.clone()
        start[:3, 3] -= 0.3 * u
        end[:3, 3] += beyond * u
        q0 = solve_ik(model, x, start, bent).q
        out[name] = (torch.stack([start, end]), (q0 / DEG).tolist())
    return out


def run_command(args: list[str]) -> tuple[int, str]:
    done = subprocess.run(TORCHCAL + args, capture_output=True, text=True, cwd=ROOT)
    return done.returncode, (done.stdout + done.stderr).strip()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--docs", type=Path, default=ROOT / "docs")
    args = parser.parse_args(argv)
    robot_file = default_robot_path()
    robot = load_robot(robot_file)
    model = ErrorModel(robot)
    x = model.nominal_vector()
    work = Path(tempfile.mkdtemp(prefix="motion_cli_"))
    results: dict = {"robot": robot.name, "runs": {}}
    try:
        cases = scenarios(model, x)
        # a calibrated twin for --model: the commands a user runs
        case, model_dir = work / "case", work / "model"
        for command in (["simulate", "--out", str(case)],
                        ["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "train.csv"),
                         "--out", str(model_dir), "residual=none"]):
            code, text = run_command(command)
            if code:
                raise SystemExit(f"torchcal {' '.join(command)} failed: {text}")
        runs = [(name, name, []) for name in cases] + [("wrist_model", "wrist", ["--model", str(model_dir)])]
        for name, geometry, extra in runs:
            poses, start = cases[geometry]
            path = work / f"{geometry}_path.csv"
            path.write_text(waypoints_csv(poses))
            out = work / f"{name}.csv"
            start_arg = "start=[" + ",".join(f"{v:.6f}" for v in start) + "]"
            shown = ["motion", "--robot", robot_file.name, *(["--model", "model"] if extra else []), "--path", path.name,
                     "--out", out.name, "start=[...]"]
            code, text = run_command(["motion", "--robot", str(robot_file), "--path", str(path), "--out", str(out),
                                      *extra, start_arg])
            metrics = json.loads((work / f"{name}_report" / "motion.json").read_text())
            entry = {"command": "torchcal " + " ".join(shown), "start_deg": start, "exit_status": code, "printed": text.splitlines(), "metrics": metrics}
            if out.is_file():
                data = np.loadtxt(out, delimiter=",", skiprows=1)
                q = data[:, 1:] * DEG
                speed, accel = rates(q, float(data[1, 0] - data[0, 0]))
                p0, p1 = poses[0, :3, 3].numpy(), poses[1, :3, 3].numpy()
                if name == "wrist_model":  # measured on the twin's true robot, in the tracker frame
                    from torchcal.sim.twin import Twin, TwinConfig
                    from torchcal.stages.store import load_model

                    twin = Twin.create(TwinConfig())
                    stored = load_model(model_dir)
                    frame = stored.model.instrument_from_base(stored.x).numpy()
                    p0, p1 = frame[:3, :3] @ p0 + frame[:3, 3], frame[:3, :3] @ p1 + frame[:3, 3]
                    tcp = twin.true_positions(torch.from_numpy(q)).numpy()
                    entry["check"] = {"frame": "tracker (twin's true robot)"}
                else:
                    tcp = mdh_fk(q)[:, :3, 3]
                    entry["check"] = {"frame": "base (second forward kinematics)"}
                error = segment_error_mm(tcp, p0, p1)
                entry["check"].update({
                    "line_error_max_mm": float(error.max()),
                    "start_error_mm": float(np.linalg.norm(tcp[0] - p0) * 1e3),
                    "end_error_mm": float(np.linalg.norm(tcp[-1] - p1) * 1e3),
                    "joint_speed_max_deg_s": float(speed.max()), "joint_accel_max_deg_s2": float(accel.max()),
                    "duration_s": float(data[-1, 0]), "q5_range_deg": [float(q[:, 4].min() / DEG), float(q[:, 4].max() / DEG)],
                })
                if name == "wrist":
                    for figure in ("path_error", "joint_speed", "joint_accel", "singularity"):
                        shutil.copyfile(work / f"{name}_report" / "figures" / f"{figure}.png",
                                        args.docs / "img" / f"motion_cli_{figure}.png")
            results["runs"][name] = entry
            print(f"{name}: exit {code}; " + "; ".join(text.splitlines()[1:3]))
        results["before_after"] = before_after(model, x, cases["wrist"])
        results["damping_sweep"] = damping_sweep(model, cases)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    atomic_write_json(args.docs / "motion_cli.json", results)
    write_section(args.docs / "motion.md", results)
    return 0


def before_after(model: ErrorModel, x_nom: torch.Tensor, case) -> dict:
    """The earlier closed-loop DLS against position-first planning on the wrist line (library calls)."""
    from torchcal.motion.clik import follow
    from torchcal.motion.config import MotionConfig
    from torchcal.motion.path import CartesianLimits, LinePath
    from torchcal.motion.planner import PlanOptions, plan_motion
    from torchcal.motion.priority import TcpKinematics

    poses, start = case
    out = {}
    for robot_name, x in (("nominal", x_nom), ("true (seed 0)", perturbed_parameters(model, 0))):
        q0 = solve_ik(model, x, poses[0], torch.tensor(start, dtype=torch.float64) * DEG).q
        kin = TcpKinematics(model.table(x), model.T_base_0, model.T_n_flange @ model.flange_from_tool(x))
        config = MotionConfig(rate_hz=250.0, limits=CartesianLimits(linear_speed=0.25, linear_accel=2.0))
        traj = LinePath(poses[0], poses[1]).sample(config.profile, config.limits, config.rate_hz)
        old = follow(model, x, traj, q0, config).trajectory.q.numpy()
        new = plan_motion(kin, model.robot, poses, PlanOptions(start=(q0 / DEG).tolist())).q
        for method, q in (("closed-loop DLS (before)", old), ("position first (torchcal motion)", new)):
            pose = kin.pose(torch.from_numpy(q)).numpy()
            speed, accel = rates(q, 0.004)
            rot = np.degrees(np.arccos(np.clip((np.trace(poses[0, :3, :3].numpy() @ np.swapaxes(pose[:, :3, :3], -1, -2),
                                                         axis1=-2, axis2=-1) - 1) / 2, -1, 1)))
            out[f"{robot_name} / {method}"] = {
                "line_error_max_mm": float(segment_error_mm(pose[:, :3, 3], poses[0, :3, 3].numpy(),
                                                            poses[1, :3, 3].numpy()).max()),
                "orientation_deviation_max_deg": float(rot.max()),
                "joint_speed_max_deg_s": float(speed.max()), "joint_accel_max_deg_s2": float(accel.max()),
                "duration_s": float((len(q) - 1) * 0.004)}
    return out


SWEEP = ((0.02, 0.02), (0.05, 0.05), (0.1, 0.1))
SWEEP_SEEDS = (0, 1, 2, 3, 4)


def damping_sweep(model: ErrorModel, cases: dict) -> dict:
    """Orientation damping against what it costs, on the wrist line executed by five true robots
    (nominal + the twin's error magnitudes, seeds 0-4): each passes the singularity at its own
    small distance, the case where the orientation must yield."""
    from torchcal.motion.planner import PlanOptions, plan_motion
    from torchcal.motion.priority import TcpKinematics

    poses, start = cases["wrist"]
    x_nom = model.nominal_vector()
    out = {}
    for eps, damping in SWEEP:
        rows = []
        for seed in SWEEP_SEEDS:
            x = perturbed_parameters(model, seed)
            kin = TcpKinematics(model.table(x), model.T_base_0, model.T_n_flange @ model.flange_from_tool(x))
            q0 = solve_ik(model, x, poses[0], torch.tensor(start, dtype=torch.float64) * DEG).q
            planned = plan_motion(kin, model.robot, poses, PlanOptions(start=(q0 / DEG).tolist(), orientation_eps=eps,
                                                                      orientation_damping=damping))
            pose = kin.pose(torch.from_numpy(planned.q)).numpy()
            rot = np.degrees(np.arccos(np.clip((np.trace(planned.targets[:, :3, :3] @ np.swapaxes(pose[:, :3, :3], -1, -2),
                                                         axis1=-2, axis2=-1) - 1) / 2, -1, 1)))
            speed, _accel = rates(planned.q, 0.004)
            rows.append([float(np.linalg.norm(pose[:, :3, 3] - planned.targets[:, :3, 3], axis=-1).max() * 1e3),
                         float(rot.max()), float(speed.max()), float(planned.t[-1])])
        arr = np.array(rows)
        exact = {}
        for name in ("wrist", "shoulder_x"):  # the nominal robot on its own lines: exact crossings
            poses_n, start_n = cases[name]
            kin = TcpKinematics(model.table(x_nom), model.T_base_0, model.T_n_flange @ model.flange_from_tool(x_nom))
            planned = plan_motion(kin, model.robot, poses_n, PlanOptions(start=start_n, orientation_eps=eps,
                                                                        orientation_damping=damping))
            pose = kin.pose(torch.from_numpy(planned.q)).numpy()
            exact[name] = float(np.degrees(np.arccos(np.clip((np.trace(
                planned.targets[:, :3, :3] @ np.swapaxes(pose[:, :3, :3], -1, -2), axis1=-2, axis2=-1) - 1) / 2, -1, 1))).max())
        out[f"eps={eps:g}, damping={damping:g}"] = {
            "nominal_wrist_orientation_deviation_max_deg": exact["wrist"],
            "nominal_shoulder_x_orientation_deviation_max_deg": exact["shoulder_x"],
            "path_error_max_mm": float(arr[:, 0].max()), "orientation_deviation_max_deg": float(arr[:, 1].max()),
            "orientation_deviation_median_deg": float(np.median(arr[:, 1])), "joint_speed_max_deg_s": float(arr[:, 2].max()),
            "duration_max_s": float(arr[:, 3].max()), "duration_median_s": float(np.median(arr[:, 3]))}
    return out


def write_section(path: Path, results: dict) -> None:
    runs = results["runs"]
    rows = ["| scenario | exit | path error max (mm) | start / end (mm) | orientation dev. max (deg) | "
            "joint speed max (deg/s) | joint accel. max (deg/s^2) | duration (s) |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name, entry in runs.items():
        m = entry["metrics"]
        check = entry.get("check")
        path_error = f"{m['path_error_max_mm']:.2g}" + (f" ({check['line_error_max_mm']:.2g})" if check else "")
        rows.append(f"| {name} | {entry['exit_status']} | {path_error} | {m['start_error_mm']:.2g} / {m['end_error_mm']:.2g} | "
                    f"{m['orientation_deviation_max_deg']:.3g} | {max(m['joint_speed_max_deg_s']):.1f} | "
                    f"{max(m['joint_accel_max_deg_s2']):.0f} | {m['duration_s']:.3f} |")
    before = ["| robot / method | line error max (mm) | orientation dev. max (deg) | joint speed max (deg/s) | "
              "joint accel. max (deg/s^2) | duration (s) |", "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for name, m in results["before_after"].items():
        before.append(f"| {name} | {m['line_error_max_mm']:.3g} | {m['orientation_deviation_max_deg']:.3g} | "
                      f"{m['joint_speed_max_deg_s']:.1f} | {m['joint_accel_max_deg_s2']:.0f} | {m['duration_s']:.3f} |")
    commands = "\n".join(f"    {entry['command']}" for entry in runs.values())
    sweep = ["| orientation_eps, orientation_damping | path error max (mm) | orientation dev. median / max (deg) | "
             "joint speed max (deg/s) | duration median / max (s) | nominal wrist / shoulder_x: orientation dev. (deg) |",
             "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for name, m in results["damping_sweep"].items():
        sweep.append(f"| {name} | {m['path_error_max_mm']:.2g} | {m['orientation_deviation_median_deg']:.3g} / "
                     f"{m['orientation_deviation_max_deg']:.3g} | {m['joint_speed_max_deg_s']:.0f} | "
                     f"{m['duration_median_s']:.3f} / {m['duration_max_s']:.3f} | "
                     f"{m['nominal_wrist_orientation_deviation_max_deg']:.3g} / "
                     f"{m['nominal_shoulder_x_orientation_deviation_max_deg']:.3g} |")
    section = "\n".join([
        BEGIN,
        "Generated by `scripts/motion_cli.py` (the figures in `docs/motion_cli.json`).",
        "",
        *rows,
        "",
        "Path error: what the command measured (its `motion.json`), in brackets the distance of the TCP from the "
        "straight segment by a second forward kinematics (textbook MDH product in NumPy read from the YAML; for "
        "`wrist_model` the twin's true robot in the tracker frame) on the joints of the written TRAJ.csv. "
        "Speeds and accelerations: finite differences of the written joints (at rest before and after). "
        "Exit 2: the command refused to write the trajectory (report written).",
        "",
        "Commands (`start=[...]` abbreviated; every value in motion_cli.json):",
        "",
        commands,
        "",
        "Same wrist line, the earlier closed-loop DLS (`torchcal.motion.follow`, S-curve at 250 mm/s and "
        "2 m/s^2) against position-first planning, measured the same way (model's own forward kinematics):",
        "",
        *before,
        "",
        "Orientation damping on the wrist line executed by five true robots (nominal plus the twin's error "
        "magnitudes, seeds 0-4; each passes q5 = 0 at its own small distance, so the orientation must yield), "
        "and the nominal robot's exact crossings of the wrist and shoulder_x lines; default: eps = damping = 0.05:",
        "",
        *sweep,
        END,
    ])
    text = path.read_text()
    if BEGIN in text:
        head, rest = text.split(BEGIN, 1)
        text = head + section + rest.split(END, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    atomic_write_text(path, text)


if __name__ == "__main__":
    raise SystemExit(main())
