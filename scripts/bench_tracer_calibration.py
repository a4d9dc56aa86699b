"""Benchmark: robot calibration from laser-tracer lengths alone vs from tracker points.

For each set-up and seed a tracer twin case is simulated (true robot, stations around a sphere of
the working volume, lengths with sigma 0.2 um + 0.3 um/m; held-out poses in the same sphere). The
robot is calibrated three ways from the *same poses*:

* ``joint``: robot, stations and dead paths directly from the lengths;
* ``two_step``: multilateration, then the tracker pipeline on points whitened by their covariance;
* ``tracker``: the tracker pipeline on points measured by a tracker of the *comparable* level:
  isotropic noise with per-axis sigma ``sqrt(tr(C_P) / 3)`` per point, ``C_P`` the 3x3 covariance
  (points gauge) that the multilateration of this very geometry predicts from the length model,
  i.e. a tracker whose points are exactly as uncertain, on average, as the multilaterated ones;
  robot repeatability (one visit instead of one per station) is added in quadrature. Like the
  tracer methods, the tracker fit is repeated with its fitted tool as nominal (see docs/tracer.md). Where beams
  were lost, the tracker measures the poses the lengths can locate (seen by >= 3 stations).

Scores on the held-out poses: the 3-D RMS of the prediction against the noise-free truth after a
rigid registration (the calibration's own accuracy), and the RMS against the noisy tracker points
of ``test.csv`` after ``--register`` (what ``torchcal evaluate --register`` reports). Writes
docs/tracer_calibration.json and docs/tracer_calibration.md.

    python scripts/bench_tracer_calibration.py [--seeds 0 1 2 3 4]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
import warnings
from dataclasses import replace
from pathlib import Path

import torch

from torchcal.core.errors import IdentifiabilityWarning
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.data.measurements import Measurements
from torchcal.identify.calibrate import calibrate
from torchcal.instruments.tracer.data import TracerData
from torchcal.instruments.tracer.joint_fit import calibrate_joint
from torchcal.instruments.tracer.multilateration import predict_covariance
from torchcal.instruments.tracer.twin_case import TracerTwinConfig, simulate_tracer_case
from torchcal.instruments.tracer.two_step import calibrate_two_step
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.mdh import link_transform
from torchcal.stages.geometry import registered_errors

DOCS = Path(__file__).resolve().parents[1] / "docs"

SETUPS = {
    "4 stations x 60 poses": {},
    "4 stations x 30 poses, 15 % lengths lost": {"n_train": 30, "loss_probability": 0.15},
    "6 stations x 60 poses": {"n_stations": 6},
    "4 stations x 60 poses, repeatability 2 um": {"repeatability_mm": 0.002},
}


def _rms(e: torch.Tensor) -> float:
    return float(e.pow(2).sum(-1).mean().sqrt())


def _scores(predict, case) -> dict:
    """Held-out RMS (um) against the noise-free truth and against test.csv, both registered."""
    pred = predict(case.test.q)
    return {
        "truth_rms_um": _rms(registered_errors(pred, case.test_true_base)) * 1e6,
        "test_rms_um": _rms(registered_errors(pred, case.test.position)) * 1e6,
    }


def _comparable_tracker_sigma(case) -> tuple[torch.Tensor, torch.Tensor]:
    """Poses a tracker comparison uses (those the lengths locate) and their per-axis sigma, m."""
    seen = torch.isfinite(case.lengths)
    rows = (seen.sum(1) >= 3).nonzero().flatten()
    cov, _ = predict_covariance(case.points_train[rows], case.stations, case.config.sigma, visible=seen[rows])
    n = rows.numel()
    var = cov.diagonal()[: 3 * n].reshape(n, 3).sum(-1) / 3.0
    return rows, (var + (case.config.repeatability_mm * 1e-3) ** 2).sqrt()


def _row1(x: torch.Tensor, model) -> torch.Tensor:
    """``T_base_1`` at ``q1 = 0`` of parameter vector ``x``."""
    rot, pos = link_transform(*x[model.layout.table_slice][:5])
    return model.T_base_0 @ tf.homogeneous(rot, pos)


def run_case(overrides: dict, seed: int) -> dict:
    config = TracerTwinConfig(seed=seed, **overrides)
    case = simulate_tracer_case(config)
    robot = case.twin.robot
    data = TracerData(case.q_train, case.lengths)
    out: dict = {"seed": seed, "n_lengths": int(torch.isfinite(case.lengths).sum())}

    start = time.perf_counter()
    joint = calibrate_joint(robot, data, sigma=config.sigma)
    t_joint = time.perf_counter() - start
    out["joint"] = {**_scores(lambda q: joint.model.tcp_position(q, joint.x), case), "time_s": t_joint,
                    "variance_factor": joint.variance_factor}
    # stations in the joint gauge: the true row 1 replaced by the nominal one moves everything rigidly
    gauge = _row1(joint.x, joint.model) @ tf.invert(_row1(case.twin.x_true, case.twin.model))
    s_true = case.stations @ gauge[:3, :3].T + gauge[:3, 3]
    out["joint"]["station_max_z"] = float(((joint.stations - s_true) / joint.station_sigmas).abs().max())

    start = time.perf_counter()
    two = calibrate_two_step(robot, data, sigma=config.sigma)
    t_two = time.perf_counter() - start
    cal = two.calibration
    out["two_step"] = {**_scores(lambda q: cal.model.tcp_position(q, cal.x), case), "time_s": t_two,
                       "variance_factor": two.variance_factor}

    gen = torch.Generator().manual_seed(10_000 + seed)
    rows, sigma_t = _comparable_tracker_sigma(case)
    clean = case.points_train[rows]
    noisy = clean + torch.randn(clean.shape, generator=gen, dtype=torch.float64) * sigma_t[:, None]
    start = time.perf_counter()
    measured = Measurements(q=case.q_train[rows], position=noisy)
    tracker = calibrate(robot, measured)
    # the same second pass as the tracer methods: analysis at the fitted (off-axis) tool
    again = calibrate(replace(robot, tool=tracker.x[tracker.model.layout.tool_slice][:3]), measured)
    tracker = again if len(again.free) > len(tracker.free) else tracker
    t_tracker = time.perf_counter() - start
    out["tracker"] = {**_scores(lambda q: tracker.model.tcp_position(q, tracker.x), case), "time_s": t_tracker,
                      "per_axis_sigma_um": float(sigma_t.pow(2).mean().sqrt()) * 1e6}
    for method in ("joint", "two_step"):
        for key in ("truth_rms_um", "test_rms_um"):
            out[method][key.replace("_um", "_ratio_to_tracker")] = out[method][key] / out["tracker"][key]
    out["tracker"]["n_poses"] = int(rows.numel())
    out["test_noise_floor_um"] = config.noise_floor_rms_mm * 1e3
    return out


def _mean(rows, method, key):
    return statistics.fmean(r[method][key] for r in rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--out", type=Path, default=DOCS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", IdentifiabilityWarning)
    results = {}
    for name, overrides in SETUPS.items():
        rows = [run_case(overrides, seed) for seed in args.seeds]
        results[name] = {"overrides": overrides, "seeds": rows}
        print(name, {m: round(_mean(rows, m, "truth_rms_um"), 3) for m in ("joint", "two_step", "tracker")})

    payload = {
        "description": "held-out RMS (um) of robots calibrated from tracer lengths (joint, two-step) and from "
                       "tracker points of the comparable level, same poses; see scripts/bench_tracer_calibration.py",
        "machine": {"python": platform.python_version(), "torch": torch.__version__, "threads": 1},
        "setups": results,
    }
    atomic_write_json(args.out / "tracer_calibration.json", payload)

    lines = [
        "# Robot calibration from laser-tracer lengths",
        "",
        "Generated by `scripts/bench_tracer_calibration.py` (seeds "
        + ", ".join(str(s) for s in args.seeds) + "). Twin: embedded KR6-like robot with random geometric "
        "errors, TCP in a 400 mm sphere of the working volume, stations 1 m from its centre, lengths with "
        "sigma 0.2 um + 0.3 um/m; 200 held-out poses in the same sphere, measured by a tracker with 1 um "
        "per axis (test noise floor 1.73 um RMS 3-D, more with repeatability).",
        "",
        "Methods, all from the same poses: **joint** (robot + stations + dead paths from the lengths), "
        "**two-step** (multilateration, then the tracker pipeline on points whitened by their 3x3 "
        "covariance), **tracker** (the tracker pipeline on points with isotropic noise of per-axis sigma "
        "`sqrt(tr C_P / 3)` per point, `C_P` the point covariance the multilateration of this geometry "
        "predicts, so the tracker is as good as the multilaterated points on average; repeatability added "
        "in quadrature; with lost beams the tracker gets the poses seen by at least three stations).",
        "",
        "`truth` = 3-D RMS of the prediction against the noise-free held-out TCP after rigid registration "
        "(the calibration's own error); `test` = RMS against the noisy `test.csv` points after "
        "registration (what `torchcal evaluate --register` reports). Ratios are to the tracker, mean over seeds.",
        "",
        "| set-up | tracker sigma/axis um | joint truth um | two-step truth um | tracker truth um | joint/tracker | two-step/tracker | joint test um | two-step test um | tracker test um | noise floor um | joint s | two-step s |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, block in results.items():
        rows = block["seeds"]
        lines.append(
            f"| {name} | {_mean(rows, 'tracker', 'per_axis_sigma_um'):.3f} "
            f"| {_mean(rows, 'joint', 'truth_rms_um'):.3f} | {_mean(rows, 'two_step', 'truth_rms_um'):.3f} "
            f"| {_mean(rows, 'tracker', 'truth_rms_um'):.3f} "
            f"| {_mean(rows, 'joint', 'truth_rms_ratio_to_tracker'):.2f} | {_mean(rows, 'two_step', 'truth_rms_ratio_to_tracker'):.2f} "
            f"| {_mean(rows, 'joint', 'test_rms_um'):.3f} | {_mean(rows, 'two_step', 'test_rms_um'):.3f} "
            f"| {_mean(rows, 'tracker', 'test_rms_um'):.3f} | {statistics.fmean(r['test_noise_floor_um'] for r in rows):.3f} "
            f"| {statistics.median(r['joint']['time_s'] for r in rows):.2f} | {statistics.median(r['two_step']['time_s'] for r in rows):.2f} |"
        )
    lines += [
        "",
        "Per seed (truth RMS, um):",
        "",
        "| set-up | seed | joint | two-step | tracker | joint station max abs z |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, block in results.items():
        for r in block["seeds"]:
            lines.append(
                f"| {name} | {r['seed']} | {r['joint']['truth_rms_um']:.3f} | {r['two_step']['truth_rms_um']:.3f} "
                f"| {r['tracker']['truth_rms_um']:.3f} | {r['joint']['station_max_z']:.2f} |"
            )
    lines += [
        "",
        "Station z-scores of the joint method are in its gauge (the robot base frame as realized by the "
        "nominal row-1 parameters): the true stations are moved by `G = T_base_1(nominal) T_base_1(true)^-1` "
        "(row 1 at q1 = 0), the rigid motion that replacing the true row 1 by the nominal one makes. Times: median seconds per fit on one CPU "
        f"thread (Python {platform.python_version()}, torch {torch.__version__}).",
        "",
    ]
    atomic_write_text(args.out / "tracer_calibration.md", "\n".join(lines))


if __name__ == "__main__":
    main()
