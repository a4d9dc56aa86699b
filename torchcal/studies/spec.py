"""What a study is: its search space, objectives, sampler, pruner and storage (``configs/study/``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from torchcal.core.errors import TorchcalError
from torchcal.core.outputs import check_name

Direction = Literal["minimize", "maximize"]
OBJECTIVES: dict[str, Direction] = {"validation_rms_mm": "minimize", "model_size": "minimize", "fit_seconds": "minimize"}
SAMPLERS = ("tpe", "random")
PRUNERS = ("none",)
_ROBOT_AND_TRAIN = "study.robot and study.train go together: give both to study measured data, or neither for the twin"


@dataclass
class StudyConfig:
    """Settings of an Optuna study.

    Attributes:
        name: study name (also its folder under ``<out>/studies/``).
        n_trials: finished trials (complete or pruned) the study aims at, over all workers and
            restarts together, as the database counts them.
        objectives: ``validation_rms_mm`` (the model ``fit`` keeps with the trial's settings,
            scored by the grouped cross-validation ``fit`` decides by, mm; or its RMS on
            ``holdout`` when given), optionally ``model_size`` (parameters of the kept head) and
            ``fit_seconds``.
        sampler: ``tpe`` or ``random``; every new trial's sampler is seeded from ``seed`` and the
            trial's number, so a one-worker study repeats and a resumed one draws new points.
        seed: seed of the sampler (with the trial number, see ``sampler``).
        pruner: ``none``. A trial is one cross-validated ``fit``; heads that cannot pass its gate
            are stopped by the gate's own futility rule.
        storage: ``None`` for SQLite in the study folder, or any SQLAlchemy URL
            (``postgresql://user@host/db``) shared by workers on several machines.
        heartbeat_interval_s / grace_period_s: a running trial whose heartbeat is older than the
            grace period is marked failed (its worker was killed) and queued again.
        max_retry: times a killed trial is queued again with the same parameters.
        reconnect_s: how long a worker keeps trying to reach a database server that went away
            before it stops with a message (the study resumes when the command is run again).
        search_space: dotted run-config key -> ``{type: int|float|categorical, low, high, step,
            log, choices}``.
        refit_best: refit the best trial as a full run (report, held-out test, export) at the end.
        robot / train / test: measured data instead of the twin: a robot file, the training
            measurement CSV (cross-validated as ``fit`` does) and optionally a test CSV (recorded,
            never optimized). Units follow ``fit.joint_unit`` / ``fit.length_unit``.
        holdout: another measurement series of the same robot (CSV): when given, the objective
            is the RMS on it of the model ``fit`` makes on ``train`` with the trial's settings.
        holdout_register: re-fit the tracker frame on the held-out series before scoring (as
            ``evaluate --register``), for a series measured with the instrument elsewhere.
    """

    name: str = "study"
    n_trials: int = 20
    objectives: list[str] = field(default_factory=lambda: ["validation_rms_mm"])
    sampler: str = "tpe"
    seed: int = 0
    pruner: str = "none"
    storage: str | None = None
    heartbeat_interval_s: int = 5
    grace_period_s: int = 20
    max_retry: int = 1
    reconnect_s: float = 60.0
    search_space: dict[str, Any] = field(default_factory=dict)
    refit_best: bool = True
    robot: str | None = None
    train: str | None = None
    test: str | None = None
    holdout: str | None = None
    holdout_register: bool = False

    def validate(self) -> None:
        check_name(self.name, "study.name")
        unknown = [o for o in self.objectives if o not in OBJECTIVES]
        if not self.objectives or unknown:
            raise TorchcalError(f"study.objectives: unknown {unknown or 'empty list'}; choose from {sorted(OBJECTIVES)}")
        if self.sampler not in SAMPLERS:
            raise TorchcalError(f"study.sampler '{self.sampler}' unknown; choose one of {SAMPLERS}")
        if self.pruner not in PRUNERS:
            raise TorchcalError(f"study.pruner '{self.pruner}': a trial is one cross-validated fit, whose gate stops "
                                "hopeless heads itself; use pruner: none")
        if self.n_trials < 1:
            raise TorchcalError("study.n_trials must be at least 1")
        if (self.robot is None) != (self.train is None):
            raise TorchcalError(_ROBOT_AND_TRAIN)
        if self.test is not None and self.train is None:
            raise TorchcalError("study.test needs study.train (the twin brings its own test poses)")
        if self.holdout is not None and self.train is None:
            raise TorchcalError("study.holdout needs study.robot and study.train (a held-out series of measured data)")
        if self.heartbeat_interval_s < 1 or self.grace_period_s <= self.heartbeat_interval_s:
            raise TorchcalError("study.heartbeat_interval_s must be at least 1 and grace_period_s longer than it")
        if not self.search_space:
            raise TorchcalError("study.search_space is empty: declare at least one parameter")
        for key, spec in self.search_space.items():
            Distribution.parse(key, spec)

    @property
    def directions(self) -> list[Direction]:
        return [OBJECTIVES[o] for o in self.objectives]

    def measured(self) -> tuple[str, str]:
        """The robot file and the training CSV of a study on measured data (``train`` given)."""
        if self.robot is None or self.train is None:
            raise TorchcalError(_ROBOT_AND_TRAIN)
        return self.robot, self.train



@dataclass(frozen=True)
class Distribution:
    """One searched parameter: a dotted run-config key and its range."""

    key: str
    kind: str
    low: float | None = None
    high: float | None = None
    step: float | None = None
    log: bool = False
    choices: tuple | None = None

    @classmethod
    def parse(cls, key: str, spec: Any) -> Distribution:
        if not isinstance(spec, dict) or "type" not in spec:
            raise TorchcalError(f"study.search_space['{key}'] needs a mapping with 'type' (int, float or categorical)")
        kind = spec["type"]
        extra = set(spec) - {"type", "low", "high", "step", "log", "choices"}
        if extra:
            raise TorchcalError(f"study.search_space['{key}']: unknown fields {sorted(extra)}")
        if kind == "categorical":
            choices = spec.get("choices")
            if not choices:
                raise TorchcalError(f"study.search_space['{key}']: categorical needs a non-empty 'choices' list")
            return cls(key, kind, choices=tuple(choices))
        if kind not in ("int", "float"):
            raise TorchcalError(f"study.search_space['{key}']: type '{kind}' unknown; use int, float or categorical")
        if "low" not in spec or "high" not in spec or not spec["low"] < spec["high"]:
            raise TorchcalError(f"study.search_space['{key}']: needs low < high")
        return cls(key, kind, spec["low"], spec["high"], spec.get("step"), bool(spec.get("log", False)))

    def _choices(self) -> tuple:
        """The choices of a categorical parameter (``parse`` always sets them)."""
        if self.choices is None:
            raise TorchcalError(f"study.search_space['{self.key}']: categorical needs a non-empty 'choices' list")
        return self.choices

    def _bounds(self) -> tuple[float, float]:
        """``(low, high)`` of an int or float parameter (``parse`` always sets them)."""
        if self.low is None or self.high is None:
            raise TorchcalError(f"study.search_space['{self.key}']: needs low < high")
        return self.low, self.high

    def contains(self, value: Any) -> bool:
        """Whether ``value`` is a point of this distribution (e.g. the default configuration's)."""
        if self.kind == "categorical":
            return value in self._choices()
        low, high = self._bounds()
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not low <= value <= high:
            return False
        if self.kind == "int" and int(value) != value:
            return False
        if self.step:
            k = (value - low) / self.step
            return abs(k - round(k)) < 1e-9
        return True

    def suggest(self, trial) -> Any:
        """The value an Optuna trial suggests for this parameter."""
        if self.kind == "categorical":
            return trial.suggest_categorical(self.key, list(self._choices()))
        low, high = self._bounds()
        if self.kind == "int":
            return trial.suggest_int(self.key, int(low), int(high), step=int(self.step or 1), log=self.log)
        return trial.suggest_float(self.key, float(low), float(high), step=self.step, log=self.log)


def search_space(config: StudyConfig) -> list[Distribution]:
    return [Distribution.parse(k, v) for k, v in config.search_space.items()]
