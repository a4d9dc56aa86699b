"""One trial of a study: the run configuration with the trial's values, scored on validation.

The objective is the validation RMS (mm) of the residual head on a held-out part of the
*training* poses: one fold of the fit's own folds (:mod:`torchcal.data.folds`,
whole configuration regions by default, so that near-twins of validation poses never train the
head), with the head fitted exactly as in the gate of ``fit`` (its own tuning on a slice of the
training part, never on the validation poses). The twin's
test poses are scored too but only recorded (``test_rms_mm``), so a study never selects on data
it is judged by. Data and the
geometric fit depend only on the twin and geometric settings, so they are computed once per
worker process and reused by every trial that shares them.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import torch

from torchcal.core.errors import TorchcalError
from torchcal.studies.spec import StudyConfig, search_space

# Fit settings that change the geometric stage; the others only change the residual head.
GEOMETRIC_KEYS = ("method", "parallel_threshold_deg", "joint_unit", "length_unit", "device", "tool_mm",
                  "gravity_compliance", "joint_harmonics", "split", "cv_folds", "cv_groups")


def apply_values(config, values: dict[str, Any]):
    """``config`` (a RunConfig) with dotted ``values`` set, type-checked by its schema."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        merged = OmegaConf.merge(OmegaConf.structured(config), OmegaConf.from_dotlist([f"{k}={v}" for k, v in values.items()]))
        return OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        raise TorchcalError(f"study.search_space: {str(exc).splitlines()[0]}") from None


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:12]


@dataclass
class PreparedData:
    """A twin case loaded and geometrically fitted, plus the residual features and split."""

    robot: Any
    result: Any
    features: Any
    x: torch.Tensor
    y: torch.Tensor
    train: torch.Tensor
    val: torch.Tensor
    x_test: torch.Tensor | None
    y_test: torch.Tensor | None


class StudyObjective:
    """Callable Optuna objective over ``base`` (a RunConfig) and ``study``'s search space."""

    def __init__(self, base, study: StudyConfig, study_dir: Path) -> None:
        self.base, self.study, self.study_dir = base, study, Path(study_dir)
        self.space = search_space(study)
        self._prepared: dict[str, PreparedData] = {}

    # -------------------------------------------------------------------- data
    def _case(self, twin_config) -> dict[str, Path]:
        from torchcal.sim.twin import write_twin_case

        folder = self.study_dir / "cases" / _digest(asdict(twin_config))
        paths = {n: folder / n for n in ("robot.yaml", "train.csv", "test.csv", "truth.json")}
        if not all(p.is_file() for p in paths.values()):
            # Deterministic for a given config, and written atomically: concurrent workers agree.
            write_twin_case(folder, twin_config)
        return paths

    def prepare(self, config) -> PreparedData:
        """Twin data and geometric fit for ``config``, computed once per distinct setting."""
        from torchcal.data.measurements import Measurements, load_measurements
        from torchcal.identify.joint_errors import JointSpaceErrors
        from torchcal.kinematics.robot import load_robot
        from torchcal.residual.features import JointFeatures
        from torchcal.stages.geometry import fit, make_config_folds, with_tool
        from torchcal.stages.residual import residual_targets_mm

        fit_geometry = {k: getattr(config.fit, k) for k in GEOMETRIC_KEYS}
        source = asdict(config.twin) if self.study.train is None else [self.study.robot, self.study.train, self.study.test]
        key = _digest([source, fit_geometry, config.fit.seed])
        if key not in self._prepared:
            units = {"joint_unit": config.fit.joint_unit, "length_unit": config.fit.length_unit}
            if self.study.train is None:
                case = self._case(config.twin)
                robot = with_tool(load_robot(case["robot.yaml"]), config.fit)
                train = load_measurements(case["train.csv"], robot)
                test: Measurements | None = load_measurements(case["test.csv"], robot)
            else:
                assert self.study.robot is not None  # validated: robot and train go together
                robot = with_tool(load_robot(self.study.robot), config.fit)
                train = load_measurements(self.study.train, robot, **units)
                test = load_measurements(self.study.test, robot, **units) if self.study.test else None
            geometry_only = replace(config.fit, residual="none")
            result = fit(robot, train, geometry_only)
            features = JointFeatures(robot.joint_limits.to(torch.float64), None)
            idx_train, idx_val = (torch.as_tensor(i) for i in make_config_folds(robot, train, geometry_only).splits()[0])
            terms = JointSpaceErrors.of(result)

            def targets(data):
                return residual_targets_mm(result.model, result.x, data, terms.effective_joints(robot, data.q))

            self._prepared[key] = PreparedData(
                robot, result, features, features(train.q, None), targets(train), idx_train, idx_val,
                features(test.q, None) if test is not None else None, targets(test) if test is not None else None,
            )
        return self._prepared[key]

    # ------------------------------------------------------------------- trial
    def __call__(self, trial) -> float | tuple[float, ...]:
        import optuna

        from torchcal.config import save_resolved_config
        from torchcal.residual.base import rms
        from torchcal.residual.selection import fit_before_gate
        from torchcal.stages.residual import _candidates

        values = {d.key: d.suggest(trial) for d in self.space}
        config = apply_values(self.base, values)
        config.fit.progress = False
        trial.set_user_attr("worker_pid", os.getpid())
        trial_dir = self.study_dir / "trials" / f"{trial.number:04d}"
        save_resolved_config(trial_dir / "config.yaml", config)
        started = time.perf_counter()
        data = self.prepare(config)
        single_objective = len(self.study.objectives) == 1
        scores: dict[str, float] = {}
        best_head, best_score = None, float("inf")
        for head in _candidates(config.fit):
            if single_objective and hasattr(head, "on_iteration"):
                def report(step: int, value: float) -> None:
                    trial.report(value, step)
                    if trial.should_prune():
                        raise optuna.TrialPruned(f"validation RMS {value:.4f} mm at iteration {step}")

                head.on_iteration = report
            # as the gate of `fit` does: tuned on a slice of the training part, scored on validation
            fit_before_gate(head, data.x[data.train], data.y[data.train], seed=config.fit.seed)
            scores[head.name] = rms(head.predict(data.x[data.val]) - data.y[data.val])
            if scores[head.name] < best_score:
                best_head, best_score = head, scores[head.name]
        seconds = time.perf_counter() - started
        size = sum(t.numel() for t in best_head.module().state_dict().values()) if best_head is not None else 0
        test_rms = None
        if data.x_test is not None and data.y_test is not None:  # set together
            test_rms = rms(best_head.predict(data.x_test) - data.y_test) if best_head is not None else rms(data.y_test)
        trial.set_user_attr("head", best_head.name if best_head is not None else None)
        trial.set_user_attr("validation_rms_by_head_mm", scores)
        trial.set_user_attr("geometric_validation_rms_mm", rms(data.y[data.val]))
        trial.set_user_attr("test_rms_mm", test_rms)
        trial.set_user_attr("model_size", size)
        trial.set_user_attr("fit_seconds", seconds)
        measured = {"validation_rms_mm": best_score, "model_size": float(size), "fit_seconds": seconds}
        out = tuple(measured[o] for o in self.study.objectives)
        return out[0] if single_objective else out
