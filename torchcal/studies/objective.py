"""One trial of a study: ``fit`` with the trial's settings, scored as ``fit`` scores its choices.

A trial runs what ``fit`` runs on the training poses, with the same code: the structure chosen
by cross-validation on the folds of ``fit.split`` (grouped configuration regions by default,
:mod:`torchcal.model_selection`), the residual heads judged on the same folds by the gate of
:mod:`torchcal.stages.residual`, and the kept head fitted on all training poses. The objective is
the cross-validated RMS (mm) of the model that gate keeps, so a study ranks configurations by the
evidence ``fit`` decides by and its best trial is a model ``fit`` would keep. With
``study.holdout`` (another measurement series of the same robot) the objective is instead the
RMS of that model on the held-out series. The twin's test poses (or ``study.test``) are scored
too but only recorded (``test_rms_mm``). The geometric part (data, structure cross-validation,
fit on all poses) depends only on the data and the geometric settings, so it is computed once
per worker process and reused by every trial that shares them.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from torchcal.config import save_resolved_config
from torchcal.core.errors import TorchcalError
from torchcal.core.hashing import sha256_file
from torchcal.core.metrics import position_metrics
from torchcal.core.threads import fit_threads
from torchcal.data.measurements import Measurements, load_measurements
from torchcal.instruments.registry import default
from torchcal.kinematics.robot import load_robot
from torchcal.stages.geometry import fit_with_selection, held_out_errors, with_tool
from torchcal.stages.pipeline import fit_model
from torchcal.stages.store import load_model
from torchcal.studies.spec import StudyConfig, apply_values, search_space

# Fit settings that only change the residual heads; every other one changes the geometric part.
HEAD_KEYS = ("residual", "head_time_check", "residual_hidden", "mayfly_population", "mayfly_iterations",
             "residual_margin", "progress")


CASE_FILES = ("robot.yaml", "train.csv", "test.csv", "truth.json")
#: user attr of a trial stopped by Ctrl-C (SIGINT), and of the trial that runs its parameters again
INTERRUPTED = "interrupted"
RETRY_OF_INTERRUPTED = "retry_of_interrupted"


def check_case(study, folder: Path) -> None:
    """Refuse a cached twin case (``cases/<digest>/``) whose files changed since the study first used it.

    The first use records the files' SHA-256 in the study's user attrs (``case:<digest>``): every
    worker, on every machine, writes the same deterministic case and checks it against that record.
    """
    sums = {n: sha256_file(folder / n) for n in CASE_FILES if (folder / n).is_file()}
    key = f"case:{folder.name}"
    stored = study.user_attrs.get(key)
    if stored is None:
        study.set_user_attr(key, sums)
        return
    changed = sorted(n for n in set(stored) | set(sums) if stored.get(n) != sums.get(n))
    if changed:
        raise TorchcalError(f"cached twin case {folder}: {', '.join(changed)} changed since the study's trials were "
                            f"scored on it (SHA-256 differs); delete {folder} to have it written again")


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:12]


def geometric_settings(fit_config) -> dict[str, Any]:
    """The fit settings the geometric part depends on."""
    return {k: v for k, v in asdict(fit_config).items() if k not in HEAD_KEYS}


@dataclass
class PreparedData:
    """Training data fitted as ``fit`` does, before its heads: structure CV and the fit on all poses."""

    robot: Any
    train: Any
    result: Any
    structure: Any
    test: Any | None
    holdout: Any | None


def same_configuration(trial, other) -> bool:
    """Whether two trials have the same parameters (the same configuration)."""
    return other.params.keys() == trial.params.keys() and all(other.params[k] == v for k, v in trial.params.items())


class StudyObjective:
    """Callable Optuna objective over ``base`` (a RunConfig) and ``study``'s search space.

    ``on_start(trial)``, if given, is called first thing in every trial (the worker hands its
    study lock back there: the trial is taken).
    """

    def __init__(self, base, study: StudyConfig, study_dir: Path, on_start=None) -> None:
        self.base, self.study, self.study_dir = base, study, Path(study_dir)
        self.space = search_space(study)
        self.on_start = on_start
        self._prepared: dict[str, PreparedData] = {}

    # -------------------------------------------------------------------- data
    def _case(self, twin_config, study=None) -> dict[str, Path]:
        digest = _digest(asdict(twin_config))
        folder = self.study_dir / "cases" / digest
        paths = {n: folder / n for n in CASE_FILES}
        if not all(p.is_file() for p in paths.values()):
            # Deterministic for a given config, and written atomically: concurrent workers agree.
            default().twin().write(folder, twin_config)
        if study is not None:
            check_case(study, folder)
        return paths

    def prepare(self, config, trial_study=None) -> PreparedData:
        """Data, structure cross-validation and fit on all poses for ``config``, once per distinct setting."""
        study = self.study
        source = asdict(config.twin) if study.train is None else [study.robot, study.train, study.test, study.holdout]
        key = _digest([source, geometric_settings(config.fit)])
        if key not in self._prepared:
            units = {"joint_unit": config.fit.joint_unit, "length_unit": config.fit.length_unit}
            test: Measurements | None
            holdout: Measurements | None = None
            if study.train is None:
                case = self._case(config.twin, study=trial_study)
                robot = with_tool(load_robot(case["robot.yaml"]), config.fit)
                train = load_measurements(case["train.csv"], robot)
                test = load_measurements(case["test.csv"], robot)
            else:
                robot_file, train_file = study.measured()
                robot = with_tool(load_robot(robot_file), config.fit)
                train = load_measurements(train_file, robot, **units)
                test = load_measurements(study.test, robot, **units) if study.test else None
                holdout = load_measurements(study.holdout, robot, **units) if study.holdout else None
            # the structure is cross-validated whatever the heads are (any head makes fit run it); on one
            # thread, as fit runs it (core.threads): split across threads these small solves spin-wait
            # for cores that the other workers hold
            with fit_threads():
                result, structure = fit_with_selection(robot, train, replace(config.fit, residual="auto", progress=False))
            self._prepared[key] = PreparedData(robot, train, result, structure, test, holdout)
        return self._prepared[key]

    # ------------------------------------------------------------------- trial
    def _repeat_of(self, trial):
        """A complete trial with this trial's configuration, if the sampler proposed one again."""
        from optuna.trial import TrialState

        for other in trial.study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
            if other.number != trial.number and same_configuration(trial, other):
                return other
        return None

    def __call__(self, trial) -> float | tuple[float, ...]:
        try:
            return self._run(trial)
        except KeyboardInterrupt:
            # Optuna fails the trial and the command stops; the next run of the command queues
            # its parameters again (runner.requeue_interrupted), as the heartbeat does for a killed one
            with contextlib.suppress(Exception):
                trial.set_user_attr(INTERRUPTED, True)
            raise

    def _run(self, trial) -> float | tuple[float, ...]:
        if self.on_start is not None:
            self.on_start(trial)
        values = {d.key: d.suggest(trial) for d in self.space}
        trial.set_user_attr("worker_pid", os.getpid())
        repeat = self._repeat_of(trial)
        if repeat is not None:
            # Asked again for a configuration already scored (TPE converging, or a small grid):
            # its result is known and deterministic, so it is recorded, not recomputed.
            trial.set_user_attr("repeat_of", repeat.number)
            for k, v in repeat.user_attrs.items():
                if k not in ("worker_pid", "default_configuration", "repeat_of", INTERRUPTED, RETRY_OF_INTERRUPTED):
                    trial.set_user_attr(k, v)
            return repeat.values[0] if len(self.study.objectives) == 1 else tuple(repeat.values)
        config = apply_values(self.base, values)
        config.fit.progress = False
        return self.score(trial, config)

    def score(self, trial, config) -> float | tuple[float, ...]:
        """Fit ``config`` as ``fit`` does and record the numbers; the objective value(s)."""
        trial_dir = self.study_dir / "trials" / f"{trial.number:04d}"
        save_resolved_config(trial_dir / "config.yaml", config)
        started = time.perf_counter()
        data = self.prepare(config, trial.study)
        fitted = fit_model(trial_dir / "model", data.robot, data.train, config.fit,
                           fitted=(data.result, data.structure))
        folder, kept = fitted.folder, fitted.head
        assert fitted.comparison is not None  # the prepared fit always cross-validates its structure
        comparison = fitted.comparison.to_dict()
        seconds = time.perf_counter() - started
        chosen = next(r for r in comparison["candidates"] if r["name"] == comparison["chosen"])
        stored = load_model(folder)
        size = sum(t.numel() for t in stored.residual.head.module().state_dict().values()) if stored.residual else 0

        def rms_mm(data_set, register: bool = False) -> float | None:
            if data_set is None:
                return None
            return position_metrics(held_out_errors(stored, data_set, register=register))["position_rms_mm"]

        holdout_rms = rms_mm(data.holdout, self.study.holdout_register)
        trial.set_user_attr("model", comparison["chosen"])
        trial.set_user_attr("head", kept)
        trial.set_user_attr("cv_rms_mm", chosen["cv_rms_mm"])
        trial.set_user_attr("cv_protocol", comparison["protocol"])
        trial.set_user_attr("cv_rms_by_candidate_mm", {r["name"]: r["cv_rms_mm"] for r in comparison["candidates"]
                                                       if r["cv_rms_mm"] == r["cv_rms_mm"]})
        trial.set_user_attr("test_rms_mm", rms_mm(data.test))
        trial.set_user_attr("holdout_rms_mm", holdout_rms)
        trial.set_user_attr("model_size", size)
        trial.set_user_attr("fit_seconds", seconds)
        score = holdout_rms if holdout_rms is not None else chosen["cv_rms_mm"]
        measured = {"validation_rms_mm": score, "model_size": float(size), "fit_seconds": seconds}
        out = tuple(measured[o] for o in self.study.objectives)
        return out[0] if len(out) == 1 else out
