"""Singularity-robust Cartesian motion on the twin-kr6: three methods along a singular line.

Scenario: a straight line, built with the nominal model through its wrist singularity
(``q5 = 0`` at the midpoint, constant approach, tool spinning about it), executed by the twin's
"true" robot (nominal + Gaussian kinematic errors). Joint commands are planned with:

* ``dls``: adaptive-damping DLS + pose feedback (the method), planned on the true/calibrated model;
* ``pinv``: undamped pseudo-inverse + the same feedback;
* ``dls_open_loop``: DLS without feedback (``K = 0``);

and, for the calibration comparison, ``dls_nominal_model``: DLS planned on the nominal model.
Path errors are those of the true robot executing the joints. Speed-limit scaling is off for
the method comparison so the raw joint speeds show (``dls_limited`` has it on).
A second table repeats the comparison on the nominal robot (the line then crosses *exactly*
through its singular pose).

Writes docs/motion.json, docs/motion.md, docs/img/motion_*.png, docs/motion.csv.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import solve_ik
from torchcal.kinematics.robot import default_robot_path, load_robot
from torchcal.motion import plots
from torchcal.motion.clik import follow
from torchcal.motion.config import MotionConfig
from torchcal.motion.metrics import path_errors, summarize
from torchcal.motion.scenario import perturbed_parameters, singular_line

ROOT = Path(__file__).resolve().parents[1]

ACCEPT_MM = 0.005


def _write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    with os.fdopen(fd, "w") as handle:
        handle.write(text)
    os.replace(tmp, path)


def run_methods(model, x_exec, path, q0_by_model, base: MotionConfig, methods: dict) -> dict:
    """Plan each method's joints and measure them on the robot ``(model, x_exec)``."""
    traj = path.sample(base.profile, base.limits, base.rate_hz)
    speed = base.speed_limits(model.robot)
    out = {}
    for name, (cfg, x_plan, q0) in methods.items():
        start = time.perf_counter()
        result = follow(model, x_plan, traj, q0, cfg)
        elapsed = time.perf_counter() - start
        joints = result.trajectory
        metrics = summarize(
            model, x_exec, joints.q, joints.qdot, traj.poses, result.sigma_min, base.damping_eps, speed, base.dt
        )
        pos, _ = path_errors(model, x_exec, joints.q, traj.poses)
        out[name] = {"result": result, "metrics": metrics, "position_error_m": pos, "seconds": elapsed}
    return {"trajectory": traj, "runs": out, "speed": speed}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=250.0, help="control rate, Hz (250 or 1000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the twin's kinematic errors")
    parser.add_argument("--docs", type=Path, default=ROOT / "docs")
    args = parser.parse_args(argv)

    robot = load_robot(default_robot_path())
    model = ErrorModel(robot)
    x_nom = model.nominal_vector()
    x_true = perturbed_parameters(model, args.seed)
    line = singular_line(model, x_nom)
    q0_true = solve_ik(model, x_true, line.path.start, line.q_start).q
    base = MotionConfig(rate_hz=args.rate, enforce_speed_limits=False)
    methods = {
        "dls": (base, x_true, q0_true),
        "pinv": (replace(base, method="pinv"), x_true, q0_true),
        "dls_open_loop": (replace(base, gain=0.0), x_true, q0_true),
        "dls_limited": (replace(base, enforce_speed_limits=True), x_true, q0_true),
        "dls_nominal_model": (base, x_nom, line.q_start),
    }
    twin = run_methods(model, x_true, line.path, None, base, methods)
    exact_methods = {k: (c, x_nom, line.q_start) for k, (c, _, _) in methods.items() if k in ("dls", "pinv", "dls_open_loop")}
    exact = run_methods(model, x_nom, line.path, None, base, exact_methods)

    def table(runs: dict) -> list[str]:
        rows = [
            "| method | max pos. error outside (mm) | max pos. error inside (mm) | max orient. error outside (deg) "
            "| peak joint speed / limit | max velocity step (deg/s) | samples inside |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for name, run in runs.items():
            m = run["metrics"]
            rows.append(
                f"| {name} | {m.max_position_error_outside_mm:.4g} | {m.max_position_error_inside_mm:.4g} | "
                f"{m.max_orientation_error_outside_deg:.3g} | {m.peak_speed_ratio:.3g} | "
                f"{m.max_velocity_step_deg_s:.4g} | {m.samples_inside}/{m.samples} |"
            )
        return rows

    sig = twin["runs"]["dls"]["result"]
    report = {
        "robot": robot.name,
        "rate_hz": base.rate_hz,
        "profile": base.profile,
        "line_length_m": line.path.length,
        "spin_deg": math.degrees(line.path.angle),
        "duration_s": float(twin["trajectory"].t[-1]),
        "gain_per_s": base.feedback_gain,
        "damping_eps": base.damping_eps,
        "damping_max": base.damping_max,
        "velocity_step_bound_deg_s": base.velocity_step_bound_deg_s,
        "speed_limits_deg_s": [math.degrees(v) for v in twin["speed"].tolist()],
        "acceptance_outside_mm": ACCEPT_MM,
        "twin_seed": args.seed,
        "min_sigma_nominal_model_on_line": exact["runs"]["dls"]["metrics"].min_sigma,
        "min_sigma_true_model_on_line": sig.sigma_min.min().item(),
        "twin": {k: {**v["metrics"].to_dict(), "seconds": v["seconds"]} for k, v in twin["runs"].items()},
        "exact_crossing": {k: {**v["metrics"].to_dict(), "seconds": v["seconds"]} for k, v in exact["runs"].items()},
    }
    dls = report["twin"]["dls"]
    report["acceptance"] = {
        "outside_error_ok": dls["max_position_error_outside_mm"] <= ACCEPT_MM,
        "speed_ok": dls["peak_speed_ratio"] <= 1.0,
        "velocity_continuity_ok": dls["max_velocity_step_deg_s"] <= base.velocity_step_bound_deg_s,
        "pinv_exceeds_speed_limit": report["twin"]["pinv"]["peak_speed_ratio"] > 1.0,
        "open_loop_drifts_more": report["twin"]["dls_open_loop"]["max_position_error_outside_mm"]
        > dls["max_position_error_outside_mm"],
    }
    docs = args.docs
    _write_text(docs / "motion.json", json.dumps(report, indent=2) + "\n")

    t = twin["trajectory"].t.numpy()
    inside = (sig.sigma_min < base.damping_eps).numpy()
    img = docs / "img"
    plots.plot_path_error(
        t, {k: v["position_error_m"].numpy() * 1e3 for k, v in twin["runs"].items() if k != "dls_limited"},
        img / "motion_path_error.png", inside, ACCEPT_MM,
    )
    plots.plot_joint_speeds(
        t, {k: twin["runs"][k]["result"].trajectory.qdot.numpy() for k in ("dls", "pinv", "dls_open_loop")},
        twin["speed"].numpy(), img / "motion_joint_speed.png", inside,
    )
    plots.plot_singularity(t, sig.sigma_min.numpy(), sig.manipulability.numpy(), base.damping_eps, img / "motion_singularity.png")
    twin["runs"]["dls"]["result"].trajectory.save_csv(docs / "motion.csv")

    acc = report["acceptance"]
    md = [
        "# Singularity-robust Cartesian motion",
        "",
        f"Generated by `scripts/motion_demo.py --rate {base.rate_hz:g} --seed {args.seed}`.",
        "",
        "## Scenario",
        "",
        f"Robot {robot.name}. A {line.path.length * 1e3:.0f} mm straight line (instrument = base frame, along x) with the tool",
        f"spinning {report['spin_deg']:.1f} deg about its approach axis, {base.profile} speed profile, "
        f"{report['duration_s']:.2f} s at {base.rate_hz:g} Hz. The line is built",
        "with the nominal model through its wrist singularity: at the midpoint q5 = 0 (axes 4 and 6",
        "collinear); q5 runs from about +20 deg to -20 deg. Smallest singular value along it:",
        f"{report['min_sigma_nominal_model_on_line']:.2e} (nominal model), {report['min_sigma_true_model_on_line']:.2e} (twin's true model).",
        "",
        "The twin's true robot (nominal + Gaussian errors: 0.3 mm lengths, 0.03 deg angles, 0.5 mm tool,",
        f"seed {args.seed}) executes the joints. Methods (all with pose feedback gain K = {base.feedback_gain:g} 1/s (K dt = 1) unless open-loop):",
        "",
        f"* **dls**: adaptive damping, a^2 = a_max^2 (1 - (sigma_min/eps)^2) below eps = {base.damping_eps:g}, a_max = {base.damping_max:g},",
        "  planned on the true (calibrated) model;",
        "* **pinv**: undamped pseudo-inverse, same feedback;",
        "* **dls_open_loop**: DLS with K = 0 (integration of the feed-forward only);",
        "* **dls_limited**: dls with joint speed-limit scaling on (the other rows show raw speeds);",
        "* **dls_nominal_model**: dls planned on the nominal model: the joints an uncalibrated robot is sent.",
        "",
        "Path errors are measured on the true robot. *Inside* = singular neighbourhood sigma_min < eps",
        "(of the planning model); *outside* = the rest of the line.",
        "",
        "## Twin: calibrated robot along the line",
        "",
        *table(twin["runs"]),
        "",
        f"Acceptance (dls): outside error <= {ACCEPT_MM} mm: {acc['outside_error_ok']}; no joint beyond its speed limit:",
        f"{acc['speed_ok']}; velocity steps <= {base.velocity_step_bound_deg_s:g} deg/s per cycle: {acc['velocity_continuity_ok']};",
        f"pinv beyond the speed limit: {acc['pinv_exceeds_speed_limit']}; open loop drifts more: {acc['open_loop_drifts_more']}.",
        "",
        "Speed limits (deg/s, KR6-like): " + ", ".join(f"{v:.0f}" for v in report["speed_limits_deg_s"]) + ".",
        "",
        "## Exact crossing: nominal robot along its own singular line",
        "",
        *table(exact["runs"]),
        "",
        "When the path crosses the singular pose exactly, the exact joint solution is smooth (q5 changes",
        "sign with q4 constant), so even the undamped inverse tracks it. The calibrated robot's singular",
        "set is not where the nominal one is: the same line passes it at a small distance, and there the",
        "exact solution must turn q4/q6 fast; the undamped inverse follows with joint speeds far beyond",
        "the limits while DLS leaves the path by a bounded amount inside the neighbourhood and returns",
        "to it, at the accuracy of the undamped method, when sigma_min is back above eps.",
        "",
        "![path error](img/motion_path_error.png)",
        "![joint speeds](img/motion_joint_speed.png)",
        "![singularity](img/motion_singularity.png)",
        "",
    ]
    _write_text(docs / "motion.md", "\n".join(md))
    print("\n".join(table(twin["runs"])))
    print(json.dumps(acc))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
