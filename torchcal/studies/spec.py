"""What a study is: its search space, objectives, sampler, pruner and storage (``configs/study/``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from torchcal.core.errors import TorchcalError, did_you_mean
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
        repeated = sorted({o for o in self.objectives if self.objectives.count(o) > 1})
        if repeated:  # the same objective twice makes a two-objective study with one front: no best trial
            raise TorchcalError(f"study.objectives: {', '.join(repeated)} given twice; give each objective once")
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
        if self.max_retry < 0:
            raise TorchcalError(f"study.max_retry must be 0 or more (times a killed trial is queued again), got {self.max_retry}")
        if self.holdout_register and self.holdout is None:
            raise TorchcalError("study.holdout_register re-fits the frame on the held-out series: give study.holdout too")
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
        where = f"study.search_space['{key}']"
        numbers = {f: spec[f] for f in ("low", "high", "step") if spec.get(f) is not None}
        for name, value in numbers.items():
            if not isinstance(value, (int, float)) or isinstance(value, bool) or value != value:
                raise TorchcalError(f"{where}: {name} must be a number, got {value!r}")
            if kind == "int" and int(value) != value:
                raise TorchcalError(f"{where}: {name} of an int parameter must be a whole number, got {value!r}")
        if "low" not in spec or "high" not in spec or not spec["low"] < spec["high"]:
            raise TorchcalError(f"{where}: needs low < high")
        log = spec.get("log", False)
        if not isinstance(log, bool):
            raise TorchcalError(f"{where}: log is true or false, got {log!r}")
        step = spec.get("step")
        if step is not None and step <= 0:
            raise TorchcalError(f"{where}: step must be > 0, got {step!r}")
        if step is not None and step > spec["high"] - spec["low"]:
            raise TorchcalError(f"{where}: step {step!r} is wider than the range [{spec['low']}, {spec['high']}]")
        if log and spec["low"] <= 0:
            raise TorchcalError(f"{where}: log: true needs low > 0 (a log scale never reaches {spec['low']!r})")
        if log and step is not None and (kind == "float" or step != 1):
            raise TorchcalError(f"{where}: log: true and a step do not go together; give one of them")
        return cls(key, kind, spec["low"], spec["high"], step, log)

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


#: Sections of the run configuration a trial's settings come from (``twin`` for twin studies only).
SEARCHED_SECTIONS = ("fit", "twin")


def apply_values(config, values: dict[str, Any]):
    """``config`` (a RunConfig) with dotted ``values`` set, type-checked by its schema."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        merged = OmegaConf.merge(OmegaConf.structured(config), OmegaConf.from_dotlist([f"{k}={v}" for k, v in values.items()]))
        return OmegaConf.to_object(merged)
    except OmegaConfBaseException as exc:
        raise TorchcalError(f"study.search_space: {str(exc).splitlines()[0]}") from None


def _option_type(parent: Any, name: str) -> Any:
    """The declared type of field ``name`` of the dataclass ``parent`` (``None`` when unknown)."""
    import typing

    try:
        return typing.get_type_hints(type(parent)).get(name)
    except (NameError, TypeError):
        value = getattr(parent, name, None)
        return type(value) if value is not None else None


def _check_value(base, key: str, value: Any) -> None:
    """Refuse ``value`` of option ``key`` when the option's own checks would (its schema and the fit's)."""
    try:
        config = apply_values(base, {key: value})
        if key.startswith("fit."):
            from torchcal.residual import head_names
            from torchcal.stages.geometry import structure_options

            if config.fit.residual != "none":
                head_names(config.fit.residual)
            structure_options(config.fit)
    except TorchcalError as exc:
        message = str(exc).removeprefix("study.search_space: ")
        raise TorchcalError(f"study.search_space['{key}']: the value {value!r} is refused: {message}") from None


def check_space(base, config: StudyConfig) -> None:
    """Refuse, before the first trial, a search space the run configuration ``base`` cannot take.

    Every parameter must name a ``fit.*`` option (or ``twin.*`` in a twin study), with a did-you-mean
    for a typo; its type must match the option's (an int option is searched as int, a flag or a name
    as categorical); the bounds and every categorical choice must pass the option's own checks; and
    the data files of a study on measured data must exist. A trial would otherwise find each of
    these only by failing.
    """
    import dataclasses

    for name in ("robot", "train", "test", "holdout"):
        path = getattr(config, name)
        if path is not None and not Path(path).is_file():
            raise TorchcalError(f"study.{name}: no file {path}")
    sections = SEARCHED_SECTIONS if config.train is None else ("fit",)
    for dist in search_space(config):
        where = f"study.search_space['{dist.key}']"
        section, _, rest = dist.key.partition(".")
        if section not in sections or not rest:
            raise TorchcalError(f"{where}: a trial's settings are {' or '.join(s + '.*' for s in sections)} options "
                                f"(the study's own options and the output folders are not searched)")
        parent, parts = getattr(base, section), rest.split(".")
        for i, part in enumerate(parts):
            names = [f.name for f in dataclasses.fields(parent)] if dataclasses.is_dataclass(parent) else []
            if part not in names:
                prefix = ".".join([section, *parts[:i]])
                raise TorchcalError(f"{where}: no option '{dist.key}'{did_you_mean(part, names, prefix + '.')}")
            if i < len(parts) - 1:
                parent = getattr(parent, part)
        declared = _option_type(parent, parts[-1])
        text = str(declared)
        if "bool" in text:
            if dist.kind != "categorical":
                raise TorchcalError(f"{where}: '{dist.key}' is a true/false option: search it as type: categorical "
                                    "with choices [true, false]")
        elif (declared is int or text in ("int", "<class 'int'>")) and dist.kind == "float":
            raise TorchcalError(f"{where}: '{dist.key}' is an int option: search it as type: int")
        values = list(dist.choices or ()) if dist.kind == "categorical" else [dist.low, dist.high]
        for value in values:
            _check_value(base, dist.key, value)
