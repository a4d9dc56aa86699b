"""``torchcal fit`` and ``evaluate`` on a single length-station file (``q1..qN, l1``).

``fit`` compares the structures of :mod:`.fit` by random-split and order-blocked
cross-validation (:mod:`.cv`), fits the one the blocked folds choose (``structure=auto``, the
default) or the one named, and writes a normal model folder (``T_reference = I``: the model lives
in the robot ``base`` frame; anchor, offset and the CV table in ``calibration.json`` under
``length_station``), so ``export`` works on it. ``evaluate`` keeps the robot and re-fits anchor
and offset to the scored file (a new set-up; the file needs
:data:`~torchcal.instruments.tracer.one_station.data.REFIT_MIN_CONFIGURATIONS` distinct joint
configurations that determine them), or with ``refit_anchor=false`` keeps those too (any
non-empty file).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from torchcal.config.compose import compose_options
from torchcal.core.errors import TorchcalError
from torchcal.core.overrides import check_range
from torchcal.identify.identifiability import analyze
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.instruments.base import FitOutcome
from torchcal.instruments.tracer.joint_fit import TracerJointProblem
from torchcal.instruments.tracer.lengths import station_distances
from torchcal.instruments.tracer.one_station.cv import compare_structures
from torchcal.instruments.tracer.one_station.data import (
    REFIT_MIN_CONFIGURATIONS,
    REFIT_PURPOSE,
    load_length_data,
)
from torchcal.instruments.tracer.one_station.fit import (
    STRUCTURES,
    check_station_determined,
    fit_station,
)
from torchcal.kinematics.robot import load_robot
from torchcal.stages.store import load_model, save_model


@dataclass
class LengthStationConfig:
    """Options of ``fit`` / ``evaluate`` on a one-station length file.

    Attributes:
        joint_unit: ``deg`` (default, the contract's) or ``rad``.
        length_unit: ``mm`` (default) or ``m``.
        structure: ``auto`` (default: the structure the order-blocked cross-validation chooses),
            ``nominal``, ``offsets`` or ``full`` (:mod:`torchcal.instruments.tracer.one_station.fit`).
        cv_folds: folds of the random-row and order-blocked cross-validation.
        seed: seed of the random-row folds.
        max_iterations: Levenberg-Marquardt cap of every fit.
        check_limits: refuse joints outside the robot file's limits (``false``: accept them).
        refit_anchor: ``evaluate`` re-fits anchor and offset to the scored file (a new set-up;
            ``false``: the fitted anchor and offset are kept).
    """

    joint_unit: str = "deg"
    length_unit: str = "mm"
    structure: str = "auto"
    cv_folds: int = 5
    seed: int = 0
    max_iterations: int = 100
    check_limits: bool = True
    refit_anchor: bool = True

    def __post_init__(self) -> None:
        """Refuse out-of-range values before any file is read."""
        check_range(self, "cv_folds", low=2, high=100)
        check_range(self, "max_iterations", low=1, high=10000)
        if self.structure != "auto" and self.structure not in STRUCTURES:
            raise TorchcalError(f"structure must be auto or one of {', '.join(STRUCTURES)}, got {self.structure!r}")


def length_station_config(overrides: list[str]) -> LengthStationConfig:
    """The options of a one-station fit or evaluation from ``key=value`` overrides."""
    return compose_options(LengthStationConfig(), list(overrides))



def fit_length_station(robot_path, data_path, out_dir, overrides, *, base_link=None, end_link=None, progress=None) -> FitOutcome:
    """Fit a single length station (and what the data support of the robot); returns the folder and result lines."""
    config = length_station_config(overrides)
    robot = load_robot(robot_path, base_link=base_link, end_link=end_link)
    data = load_length_data(data_path, robot, joint_unit=config.joint_unit, length_unit=config.length_unit,
                            check_limits=config.check_limits)
    if progress is not None:
        progress(f"cross-validating structures on {len(data)} lengths (random and order-blocked folds)")
    comparison = compare_structures(robot, data, k=config.cv_folds, seed=config.seed,
                                    max_iterations=config.max_iterations)
    structure = comparison["chosen"] if config.structure == "auto" else config.structure
    fit = fit_station(robot, data, structure, max_iterations=config.max_iterations)
    ident = fit.identifiability
    meta = {
        "method": "lm",
        "measurement": "length_station",
        "data": {"file": data.source, "sha256": data.sha256, "n_poses": len(data)},
        "identifiability": (lambda m: {**m, "not_identifiable": {
            "base_x, base_y, base_z, base_rx, base_ry, base_rz, alpha1, a1, theta1, d1":
                ["the anchor (a rigid motion of the robot moves the anchor with it)"], **m["not_identifiable"]}})(
            ident.to_metadata()),
        "residual_sigma_mm": fit.length_rms_m * 1e3,
        "solver": {"iterations": fit.solve.iterations, "message": fit.solve.message, "cost_history": fit.solve.history},
        "notes": fit.notes,
        "length_station": {
            "model": "l1 = |P(q) - anchor| + offset; P the tool point (cable attachment), base frame",
            "structure": structure,
            "structure_choice": "user" if config.structure != "auto" else comparison["rule"],
            "cross_validation": comparison,
            "anchor_mm": (fit.anchor * 1e3).tolist(),
            "anchor_sigma_mm": (fit.anchor_sigma * 1e3).tolist(),
            "offset_mm": fit.offset * 1e3,
            "offset_sigma_mm": fit.offset_sigma * 1e3,
            "length_rms_mm": fit.length_rms_m * 1e3,
        },
    }
    folder = save_model(Path(out_dir), robot, fit.model, fit.x, fit.free, fit.covariance, meta, training_q=data.q)
    rows = [f"  {r['structure']:8s} random {r['random_cv_rms_mm']:.3f} mm   order-blocked {r['blocks_cv_rms_mm']:.3f} mm"
            for r in comparison["rows"]]
    return FitOutcome(folder, [
        ident.summary(),
        f"{config.cv_folds}-fold held-out length RMS:\n" + "\n".join(rows)
        + f"\nstructure: {structure} ({'user' if config.structure != 'auto' else comparison['rule']}); "
        f"fitted length RMS {fit.length_rms_m * 1e3:.3f} mm"])


def evaluate_length_station(model_dir, data_path, overrides, *, register: bool = False) -> dict:
    """Length residuals of a model folder on a one-station file (anchor and offset re-fitted by default).

    Raises:
        DataError: besides the file's own problems, too few distinct joint configurations to re-fit
            anchor and offset (:data:`REFIT_MIN_CONFIGURATIONS`), or configurations that cannot
            determine them; with ``refit_anchor=false`` one row is enough.
    """
    config = length_station_config(overrides)
    stored = load_model(model_dir)
    refit = config.refit_anchor or register
    data = load_length_data(data_path, stored.robot, joint_unit=config.joint_unit, length_unit=config.length_unit,
                            check_limits=config.check_limits,
                            min_configurations=REFIT_MIN_CONFIGURATIONS if refit else 1,
                            purpose=REFIT_PURPOSE if refit else "evaluate")
    meta = stored.metadata.get("length_station")
    if meta is None:
        raise TorchcalError(f"{model_dir}: not a length-station model (fit one on a q1..qN, l1 file)")
    anchor = torch.tensor(meta["anchor_mm"], dtype=torch.float64) * 1e-3
    dead = torch.tensor([-meta["offset_mm"] * 1e-3], dtype=torch.float64)
    if refit:
        p = stored.model.layout.size
        problem = TracerJointProblem(stored.model, data.q, data.lengths, torch.full_like(data.lengths, 1e3),
                                     torch.arange(p, p + 4))
        z0 = torch.cat([stored.x, anchor, dead])
        check_station_determined(analyze(problem.jacobian(z0)[1], problem.names), data,
                                 "the anchor and offset that evaluate re-fits (refit_anchor=false keeps the fitted ones)")
        z = LevenbergMarquardt(max_iterations=config.max_iterations).solve(problem, z0).x
        _, s, d = problem.split(z)
        anchor, dead = s[0], d
    points = stored.model.tcp_position(data.q, stored.x)
    err = station_distances(points, anchor.reshape(1, 3))[:, 0] - dead[0] - data.lengths[:, 0]
    return {
        "n_poses": len(data),
        "length_rms_mm": float(err.pow(2).mean().sqrt()) * 1e3,
        "length_mean_abs_mm": float(err.abs().mean()) * 1e3,
        "length_max_mm": float(err.abs().max()) * 1e3,
        "anchor_mm": (anchor * 1e3).tolist(),
        "offset_mm": -float(dead[0]) * 1e3,
        "note": "robot fixed; anchor and offset re-fitted to this file" if refit else "robot, anchor and offset fixed",
        "model": str(model_dir),
        "data": str(data_path),
        "registered": refit,
    }

