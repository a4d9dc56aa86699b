"""Socket self-calibration on the MUKCa recordings: ``python scripts/validate_sockets.py --data-root ../shared/data/real``.

Reads ``mukca-sockets/sockets_<robot>.csv`` in place (nothing is copied). For every robot id:
the source's protocol (fit on one placement, score every other placement) for each placement
as the training one, and leave-one-placement-out. Scores are those of ``torchcal evaluate`` on
socket files (:mod:`torchcal.instruments.sockets.metrics`); the fit is the default of
``torchcal fit`` (:class:`torchcal.instruments.sockets.commands.SocketsFitConfig`). Writes
``docs/validation_sockets.json`` and the section between the socket markers of
``docs/validation.md``.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from pathlib import Path

import torch

from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.instruments.sockets.commands import SocketsFitConfig
from torchcal.instruments.sockets.data import load_socket_data
from torchcal.instruments.sockets.fit import fit_sockets_data
from torchcal.instruments.sockets.metrics import socket_metrics
from torchcal.kinematics.robot import load_robot

START, END = "<!-- sockets-table:start -->", "<!-- sockets-table:end -->"
WIRE_START, WIRE_END = "<!-- drawwire-table:start -->", "<!-- drawwire-table:end -->"
URDF = {"panda": "panda.urdf", "kuka": "iiwa14.urdf", "dinova": "gen3lite.urdf"}


def _robot(root: Path, robot_id: str):
    family = robot_id.split("_")[0]
    return load_robot(root / "raw" / "urdf" / URDF[family], end_link="ball_link"), URDF[family]


def _fit(robot, data, config: SocketsFitConfig):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit_sockets_data(robot, data, distance_mm=config.distance_mm, distance_weight=config.distance_weight,
                                parallel_threshold_deg=config.parallel_threshold_deg, tolerance=config.identifiability_tolerance,
                                gravity_points=config.gravity_points, max_iterations=config.max_iterations)


def _scores(robot, fit, data) -> tuple[dict, dict]:
    q = data.q
    nominal = socket_metrics(robot.tcp_position(q), data)
    calibrated = socket_metrics(fit.model.tcp_position(JointSpaceErrors.of(fit).effective_joints(robot, q), fit.x), data)
    return nominal, calibrated


def run_robot(root: Path, robot_id: str, config: SocketsFitConfig) -> dict:
    robot, urdf = _robot(root, robot_id)
    # recorded joints were reached by the robot; gen3lite.urdf's q6 limits are narrower than the arm's
    data = load_socket_data(root / f"sockets_{robot_id}.csv", robot, check_limits=False)
    all_nominal = socket_metrics(robot.tcp_position(data.q), data)
    out = {"robot_id": robot_id, "urdf": urdf, "n_rows": len(data), "placements": list(data.placements),
           "nominal_all": {k: v for k, v in all_nominal.items() if k != "per_placement"},
           "one_to_others": [], "leave_one_out": []}
    paired = {p for p, _, _ in data.pairs()}
    for train in data.placements:
        others = [p for p in data.placements if p != train]
        if not others or train not in paired:
            continue
        tr, te = data.select_placements([train]), data.select_placements(others)
        t0 = time.perf_counter()
        fit = _fit(robot, tr, config)
        seconds = time.perf_counter() - t0
        (_, cal_tr), (nom_te, cal_te) = _scores(robot, fit, tr), _scores(robot, fit, te)
        out["one_to_others"].append({"train": train, "n_train": len(tr), "n_test": len(te), "fit_s": seconds,
                                     "n_parameters": len(fit.free), "train_consistency_mm": cal_tr["consistency_mean_mm"],
                                     "nominal": nom_te, "calibrated": cal_te})
    if len(data.placements) >= 3:
        for held in data.placements:
            rest = [p for p in data.placements if p != held]
            tr, te = data.select_placements(rest), data.select_placements([held])
            if not tr.pairs():
                continue
            fit = _fit(robot, tr, config)
            nom_te, cal_te = _scores(robot, fit, te)
            out["leave_one_out"].append({"held_out": held, "n_train": len(tr), "n_test": len(te),
                                         "nominal": nom_te, "calibrated": cal_te})
    return out


def _f(v: float) -> str:
    return "-" if math.isnan(v) else f"{v:.3f}"


def section(results: list[dict]) -> str:
    lines = [
        START,
        "",
        "Fit: `torchcal fit` defaults on a socket file (per-joint MDH errors, ball offset, one point per (placement,",
        "socket), 50 mm scale; base frame and table row 1 are the gauge and stay nominal; columns whose scaled",
        "independent part is below 1e-3 stay nominal). Consistency: mean distance (mm) of each configuration's",
        "ball centre from its group's mean on the scored rows; distortion: mean | |c0 - c1| - 50 mm | (mm).",
        "",
        "**Source protocol: fit on one placement, score each other placement** (mean over the scored rows / placements)",
        "",
        "| robot | fitted on | n fit | fit consistency | scored rows | consistency nominal -> calibrated | distortion nominal -> calibrated |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        if not r["one_to_others"]:
            n = r["nominal_all"]
            lines.append(f"| {r['robot_id']} | (one placement only: nothing to score) | {r['n_rows']} | | | "
                         f"{_f(n['consistency_mean_mm'])} nominal | {_f(n['distortion_mean_mm'])} nominal |")
        for row in r["one_to_others"]:
            nom, cal = row["nominal"], row["calibrated"]
            lines.append(f"| {r['robot_id']} | {row['train']} | {row['n_train']} | {_f(row['train_consistency_mm'])} | "
                         f"{row['n_test']} | {_f(nom['consistency_mean_mm'])} -> **{_f(cal['consistency_mean_mm'])}** | "
                         f"{_f(nom['distortion_mean_mm'])} -> **{_f(cal['distortion_mean_mm'])}** |")
    lines += ["", "**Leave one placement out** (fit on all other placements, score the held-out one; robots with >= 3 placements)", "",
              "| robot | held out | n fit | n scored | consistency nominal -> calibrated | distortion nominal -> calibrated |",
              "|---|---|---|---|---|---|"]
    for r in results:
        for row in r["leave_one_out"]:
            nom, cal = row["nominal"], row["calibrated"]
            lines.append(f"| {r['robot_id']} | {row['held_out']} | {row['n_train']} | {row['n_test']} | "
                         f"{_f(nom['consistency_mean_mm'])} -> **{_f(cal['consistency_mean_mm'])}** | "
                         f"{_f(nom['distortion_mean_mm'])} -> **{_f(cal['distortion_mean_mm'])}** |")
        if r["leave_one_out"]:
            mean = sum(x["calibrated"]["consistency_mean_mm"] for x in r["leave_one_out"]) / len(r["leave_one_out"])
            lines.append(f"| {r['robot_id']} | mean over placements | | | **{_f(mean)}** | |")
    lines += ["", END]
    return "\n".join(lines)


def drawwire(root: Path) -> dict:
    """Random-split and order-blocked 5-fold CV of every length-station structure on the IRB 120 cable file."""
    from torchcal.instruments.tracer.one_station.cv import compare_structures
    from torchcal.instruments.tracer.one_station.data import load_length_data

    folder = root / "robotcali-irb120-cable"
    robot = load_robot(folder / "robot.yaml")
    data = load_length_data(folder / "lengths.csv", robot)
    return {"file": "robotcali-irb120-cable/lengths.csv", "n": len(data), **compare_structures(robot, data)}


def drawwire_section(result: dict) -> str:
    lines = [WIRE_START, "", (f"`{result['file']}` ({result['n']} rows, one draw-wire): held-out length RMS (mm), "
             f"{result['k']}-fold CV; anchor, attachment point and offset are fitted in every structure."), "",
             "| structure | robot parameters fitted | random rows | contiguous blocks of recording order |",
             "|---|---|---|---|"]
    what = {"nominal": "none (nominal robot)", "offsets": "joint zero offsets theta2..theta6",
            "full": "every identifiable MDH parameter"}
    for r in result["rows"]:
        mark = " (default: `fit` chooses it)" if r["structure"] == result["chosen"] else ""
        lines.append(f"| {r['structure']}{mark} | {what[r['structure']]} | {r['random_cv_rms_mm']:.3f} | "
                     f"{r['blocks_cv_rms_mm']:.3f} |")
    lines += ["", f"Rule: {result['rule']}.", "", WIRE_END]
    return "\n".join(lines)


def write_page(page: Path, text: str, heading: str, start: str = START, end: str = END) -> None:
    old = page.read_text() if page.is_file() else ""
    if start in old and end in old:
        new = old[: old.index(start)] + text + old[old.index(end) + len(end):]
    else:
        new = old.rstrip("\n") + f"\n\n{heading}\n\n" + text + "\n"
    atomic_write_text(page, new)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-root", type=Path, default=Path("../shared/data/real"))
    parser.add_argument("--docs", type=Path, default=Path("docs"))
    parser.add_argument("--robots", nargs="*", default=None)
    parser.add_argument("--only", choices=("sockets", "drawwire"), default=None)
    args = parser.parse_args()
    torch.set_num_threads(2)
    if args.only != "sockets":
        result = drawwire(args.data_root)
        atomic_write_json(args.docs / "validation_drawwire.json", result)
        write_page(args.docs / "validation.md", drawwire_section(result),
                   "## One draw-wire length station (IRB 120): random split against recording order",
                   WIRE_START, WIRE_END)
        if args.only == "drawwire":
            return
    root = args.data_root / "mukca-sockets"
    ids = args.robots or sorted(p.stem[len("sockets_"):] for p in root.glob("sockets_*.csv"))
    config = SocketsFitConfig()
    results = []
    for robot_id in ids:
        t0 = time.perf_counter()
        results.append(run_robot(root, robot_id, config))
        print(f"{robot_id}: {time.perf_counter() - t0:.1f} s", flush=True)
    atomic_write_json(args.docs / "validation_sockets.json", results)
    write_page(args.docs / "validation.md", section(results),
               "## Socket self-calibration without an instrument (MUKCa)")


if __name__ == "__main__":
    main()
