"""``torchcal fit`` and ``evaluate`` for laser-tracer length files (kind ``tracer``).

``fit`` identifies the robot from lengths alone, by the joint method (default) or in two steps
(``tracer_method=two_step|joint``), and writes a normal model folder (same format as a tracker
fit, so ``evaluate --register`` and ``export`` work on it) with the stations, dead paths and their
sigmas in ``calibration.json`` under ``tracer``. ``evaluate`` on a length file keeps the robot
fixed, fits only stations and dead paths (a new tracer set-up, the analogue of ``--register``) and
reports the length residuals.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from torchcal.config.compose import compose_options
from torchcal.config.schema import FitConfig
from torchcal.core.errors import DataError, TorchcalError
from torchcal.core.metrics import distance_summary
from torchcal.identify import IDENTIFIERS
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.instruments.base import FitOutcome
from torchcal.instruments.tracer.data import load_tracer_data
from torchcal.instruments.tracer.joint_fit import (
    TracerJointProblem,
    calibrate_joint,
    start_stations,
)
from torchcal.instruments.tracer.lengths import LengthSigma, station_distances
from torchcal.instruments.tracer.two_step import calibrate_two_step
from torchcal.kinematics.robot import load_robot
from torchcal.stages.geometry import with_tool
from torchcal.stages.store import load_model, save_model


@dataclass
class TracerFitConfig(FitConfig):
    """Options of ``torchcal fit`` on a tracer file: every tracker option plus the tracer's own.

    Attributes:
        tracer_method: ``joint`` (robot, stations and dead paths from the lengths; default) or
            ``two_step`` (multilaterate, then fit the robot to the whitened points).
        sigma_constant_um / sigma_per_m_um: length noise model ``sigma(L) = c + k L`` (weights;
            covariances are scaled a posteriori).
        triangle_tolerance_mm: slack of the triangle-inequality check of the loader.
        max_iterations: Levenberg-Marquardt cap of the joint method.

    A file with one station (``l1`` alone) is the instrument ``length_station``, with its own
    options (:class:`torchcal.instruments.tracer.one_station.commands.LengthStationConfig`).
    """

    tracer_method: str = "joint"
    sigma_constant_um: float = 0.2
    sigma_per_m_um: float = 0.3
    triangle_tolerance_mm: float = 20.0
    max_iterations: int = 100

    @property
    def sigma(self) -> LengthSigma:
        try:
            return LengthSigma(self.sigma_constant_um * 1e-6, self.sigma_per_m_um * 1e-6)
        except ValueError as exc:
            raise TorchcalError(str(exc)) from None


def tracer_config(overrides: list[str]) -> TracerFitConfig:
    config = compose_options(TracerFitConfig(), overrides)
    if config.tracer_method not in ("joint", "two_step"):
        raise TorchcalError(f"tracer_method must be 'joint' or 'two_step', got {config.tracer_method!r}")
    return config


def _station_meta(stations, station_sigmas, dead, dead_sigmas) -> dict:
    return {
        "stations_mm": (stations * 1e3).tolist(),
        "station_sigmas_mm": (station_sigmas * 1e3).tolist(),
        "dead_paths_mm": (dead * 1e3).tolist(),
        "dead_path_sigmas_mm": (dead_sigmas * 1e3).tolist(),
    }


def fit_tracer(robot_path, data_path, out_dir, overrides, *, base_link=None, end_link=None, progress=None) -> FitOutcome:
    """Fit a robot from a tracer length file and write the model folder; returns it and the result lines."""
    config = tracer_config(overrides)
    robot = with_tool(load_robot(robot_path, base_link=base_link, end_link=end_link), config)
    data = load_tracer_data(data_path, robot, joint_unit=config.joint_unit, length_unit=config.length_unit,
                            triangle_tolerance_mm=config.triangle_tolerance_mm)
    sigma = config.sigma
    notes: list[str] = []
    if config.residual not in ("auto", "none"):
        raise TorchcalError(f"residual={config.residual}: a learned residual needs point data; use residual=none with lengths")
    if config.residual == "auto":
        notes.append("no learned residual: lengths give no per-pose position targets")
    if progress is not None:
        progress(f"identifying {robot.name} from {int(data.seen.sum())} lengths of {len(data)} poses ({config.tracer_method})")
    if True:
        if config.tracer_method == "joint":
            if config.method != "lm":
                notes.append(f"method={config.method} ignored: the joint method is solved by Levenberg-Marquardt")
            res = calibrate_joint(robot, data, sigma=sigma, parallel_threshold_deg=config.parallel_threshold_deg,
                                  max_iterations=config.max_iterations, device=config.device)
            model, x, free, cov, solve, ident = res.model, res.x, res.free, res.covariance, res.solve, res.identifiability
            notes += res.notes
            tracer = {
                "method": "joint",
                "gauge": "stations in the robot base frame; base_* fixed at zero (T_reference = I); row-1 MDH "
                         "parameters confounded with the stations stay at nominal",
                **_station_meta(res.stations, res.station_sigmas, res.dead_paths, res.dead_path_sigmas),
                "variance_factor": res.variance_factor,
                "length_rms_um": res.length_rms_m * 1e6,
                "n_lengths_used": int(res.used.sum()),
                "rejected": _rejected(data, res.rejected),
            }
            residual_sigma_mm = res.length_rms_m * 1e3
        else:
            if config.method not in IDENTIFIERS:
                raise DataError(f"unknown method '{config.method}'; choose one of {sorted(IDENTIFIERS)}")
            res2 = calibrate_two_step(robot, data, sigma=sigma, identifier=IDENTIFIERS[config.method](),
                                      parallel_threshold_deg=config.parallel_threshold_deg, device=config.device)
            cal, ml = res2.calibration, res2.multilateration
            model, x, free, cov, solve, ident = cal.model, cal.x, cal.free, cal.covariance, cal.solve, cal.identifiability
            notes += cal.notes
            tracer = {
                "method": "two_step",
                "gauge": "multilaterated points fitted to the nominal TCP; the robot fit estimates that frame "
                         "(base_*) as a tracker fit does; stations mapped into the calibrated base frame",
                **_station_meta(res2.stations, res2.station_sigmas, res2.dead_paths, res2.dead_path_sigmas),
                "variance_factor": res2.variance_factor,
                "length_rms_um": ml.residual_rms * 1e6,
                "point_rms_sigma_um": ml.point_rms_sigma * res2.variance_factor**0.5 * 1e6,
                "whitened_sigma": cal.sigma_residual_m,
                "n_poses_located": int(res2.rows.numel()),
                "rejected": _rejected(data, ml.rejected, rows=res2.located_rows),
            }
            residual_sigma_mm = res2.point_residual_rms_m * 1e3
    tracer["length_sigma"] = {"constant_um": config.sigma_constant_um, "per_m_um": config.sigma_per_m_um}
    meta = {
        "method": "lm" if config.tracer_method == "joint" else config.method,
        "measurement": "tracer",
        "data": {"file": data.source, "sha256": data.sha256, "n_poses": len(data), "n_lengths": int(data.seen.sum())},
        "identifiability": ident.to_metadata(),
        "residual_sigma_mm": residual_sigma_mm,
        "solver": {"iterations": solve.iterations, "message": solve.message, "cost_history": solve.history},
        "notes": notes,
        "tracer": tracer,
    }
    folder = save_model(Path(out_dir), robot, model, x, free, cov, meta, training_q=data.q)
    return FitOutcome(folder, [
        ident.summary(),
        (f"{config.tracer_method}: length RMS {tracer['length_rms_um']:.3f} um, variance factor {tracer['variance_factor']:.3g}, "
         f"{len(free)} robot parameters, {data.n_stations} stations"),
    ])


def _rejected(data, rejected: torch.Tensor, rows: torch.Tensor | None = None) -> list[dict]:
    out = []
    for i, j in rejected.tolist():
        i = int(rows[i]) if rows is not None else i
        out.append({"row": data.line(i), "column": f"l{j + 1}"})
    return out


def evaluate_tracer(model_dir, data_path, overrides, *, register: bool = False) -> dict:
    """Length residuals of a model on a tracer file, stations and dead paths re-fitted."""
    config = tracer_config(overrides)
    stored = load_model(model_dir)
    data = load_tracer_data(data_path, stored.robot, joint_unit=config.joint_unit, length_unit=config.length_unit,
                            triangle_tolerance_mm=config.triangle_tolerance_mm)
    sigma = config.sigma
    points = stored.model.tcp_position(data.q, stored.x)
    s0, d0, used = start_stations(data, points, sigma)
    m, p = data.n_stations, stored.model.layout.size
    inv_sigma = torch.where(used, 1.0 / sigma(station_distances(points, s0)), torch.zeros_like(data.lengths))
    free = torch.arange(p, p + 4 * m)
    problem = TracerJointProblem(stored.model, data.q, torch.where(used, data.lengths, torch.nan), inv_sigma, free)
    z = LevenbergMarquardt(max_iterations=config.max_iterations).solve(problem, torch.cat([stored.x, s0.reshape(-1), d0])).x
    _, s, d = problem.split(z)
    err = (station_distances(points, s) - d - data.lengths)[used]
    out = {
        "n_poses": len(data),
        "n_lengths": int(used.sum()),
        **distance_summary(err.abs() * 1e3, "length", mean_key="mean_abs"),
        "stations_mm": (s * 1e3).tolist(),
        "dead_paths_mm": (d * 1e3).tolist(),
        "note": "robot fixed; stations and dead paths re-fitted to this file (a tracer set-up has no fixed frame)",
        "model": str(model_dir),
        "data": str(data_path),
        "registered": True,
    }
    return out

