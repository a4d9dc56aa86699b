"""Configuration dataclasses of the tracker fit (``torchcal fit``) and the main job (``torchcal run``).

They are the schema the YAML files under ``configs/`` and ``key=value`` overrides merge into
(:mod:`torchcal.config.compose`). The fit's options are split by concern (units, validation,
structure, prior, heads, search, uncertainty, runtime), one dataclass each with its own checks;
``FitConfig`` composes all of them and an instrument composes those it uses, its keys staying flat.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from torchcal.core.errors import TorchcalError
from torchcal.core.overrides import check_range
from torchcal.data.splits import SPLITS
from torchcal.sim.twin_config import TwinConfig


@dataclass
class _Checked:
    """End of the chain of ``__post_init__`` checks: each concern below checks its own fields and
    hands on, so a configuration composed of several concerns checks all of them."""

    def __post_init__(self) -> None:
        pass


@dataclass
class UnitOptions(_Checked):
    """Units of a measurement file.

    Attributes:
        joint_unit: ``deg`` or ``rad``, the joint columns ``q*``.
        length_unit: ``mm`` or ``m``, the file's lengths.
    """

    joint_unit: str = "deg"
    length_unit: str = "mm"

    def __post_init__(self) -> None:
        if self.joint_unit not in ("deg", "rad"):
            raise TorchcalError(f"joint_unit must be 'deg' or 'rad', got {self.joint_unit!r}")
        if self.length_unit not in ("mm", "m"):
            raise TorchcalError(f"length_unit must be 'mm' or 'm', got {self.length_unit!r}")
        super().__post_init__()


@dataclass
class ValidationOptions(_Checked):
    """How the cross-validation behind every choice forms its folds (:mod:`torchcal.data.folds`).

    Attributes:
        split: ``grouped`` (default; near-twin configurations in one fold), ``blocks`` (contiguous
            blocks of the file's row order, for data that drifts while measured) or ``random``
            (rows; for comparison only).
        cv_folds: folds of that cross-validation.
        cv_groups: configuration regions (k-means clusters) of ``split=grouped``.
        seed: seed of the folds and of stochastic heads.
    """

    split: str = "grouped"
    cv_folds: int = 5
    cv_groups: int = 20
    seed: int = 0

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise TorchcalError(f"split must be one of {', '.join(SPLITS)}, got {self.split!r}")
        check_range(self, "cv_folds", low=2, high=100)
        check_range(self, "cv_groups", low=1)
        super().__post_init__()


@dataclass
class StructureOptions(_Checked):
    """What the robot model holds besides the MDH geometry, and how it is identified.

    Attributes:
        method: identifier: ``lm`` (default), ``gn`` or ``lasso``.
        parallel_threshold_deg: Hayati switch (see :mod:`torchcal.kinematics.error_model`).
        tool_mm: nominal TCP in the flange frame (mm) replacing the robot file's (a URDF has none).
        gravity_compliance: joint compliance under the arm's own weight, identified with the
            geometry (:mod:`torchcal.identify.compliance`): ``none``, ``wrist``, ``elbow+wrist``,
            ``elbow+forearm+wrist`` (a third weight at the wrist centre, loading joints 1-3),
            ``elbow+wrist+cubic`` (nonlinear: a ``tau^3`` term; never chosen by ``auto``) or ``auto``
            (default: chosen by the cross-validation, with the harmonics).
        joint_harmonics: periodic joint errors ``sum_k a_kj sin(k q_j) + b_kj cos(k q_j)`` (rad),
            every joint but the last, identified with the geometry (:mod:`torchcal.identify.harmonics`):
            ``none``, ``first``, ``fourier2`` .. ``fourier4`` (a learned series with a smoothness
            prior) or ``auto`` (default: none, first, fourier2). With ``auto`` (here or in
            ``gravity_compliance``) the cross-validation compares the options and keeps the
            simplest within noise of the best (:mod:`torchcal.model_selection.compare`). The
            exported compensator carries both terms (:mod:`torchcal.compensate.joint_error_graph`).
        harmonic_min_range_deg: first harmonics only on joints whose range in the data spans at
            least this (deg): over a shorter arc a harmonic is an offset and a slope that
            extrapolates wildly (:func:`~torchcal.identify.joint_fit.fit_joint_errors`).
        series_tool / series_frame: with several measurement files of one robot (``--data``
            repeated, :mod:`torchcal.stages.series`): ``series_frame=per_series`` (each series its
            own instrument frame, registered in every solve: the tracker moved) or ``shared`` (one
            frame: it stayed); ``series_tool=shared`` (one tool) or ``per_series`` (a tool offset per
            series: a re-mounted probe). ``auto`` (default, both): from each series' nominal fit,
            one frame where the frames agree within 10 mm at the points and one tool where the tools
            agree within 5 mm (:func:`~torchcal.stages.series.resolve_set_ups`).
    """

    method: str = "lm"
    parallel_threshold_deg: float = 2.0
    tool_mm: list[float] | None = None
    gravity_compliance: str = "auto"
    joint_harmonics: str = "auto"
    harmonic_min_range_deg: float = 180.0
    series_tool: str = "auto"
    series_frame: str = "auto"

    def __post_init__(self) -> None:
        check_range(self, "parallel_threshold_deg", low=0.0, high=90.0, high_open=True)
        check_range(self, "harmonic_min_range_deg", low=0.0)
        if self.tool_mm is not None and (len(self.tool_mm) != 3 or not all(math.isfinite(v) for v in self.tool_mm)):
            raise TorchcalError(f"tool_mm needs 3 finite values (x, y, z in mm), got {list(self.tool_mm)}")
        super().__post_init__()


@dataclass
class PriorOptions(_Checked):
    """What the fit knows before the data (:mod:`torchcal.stages.prior_options`).

    Attributes:
        prior: ``tolerance`` (default: manufacturing tolerances per parameter kind), ``none`` (the rank
            cut of earlier versions) or an earlier model folder (its parameters and covariance).
        prior_scale: ``auto`` (default: the marginal likelihood, evidence, chooses between the nominal
            robot and the tolerances scaled x0.25, x1, x4, x16), ``cv`` (the same candidates by the
            grouped cross-validation, one fit per candidate and fold), ``nominal`` or a number
            multiplying the MDH sigmas.
        tolerance_length_mm: prior 1-sigma of MDH lengths a, d (mm; overrides the robot file's
            ``calibration_prior`` and the default 0.5).
        tolerance_angle_deg: prior 1-sigma of MDH angles alpha, beta (deg; default 0.05).
        tolerance_joint_offset_deg: prior 1-sigma of joint zero offsets theta (deg; default 0.1).
        tolerance_tool_mm: prior 1-sigma of the tool point per axis (mm; default 10).
        tolerance_tool_deg: prior 1-sigma of the tool rotation, orientation data only (deg; default: none,
            the probe's mounting angle is the orientations' to find).
    """

    prior: str = "tolerance"
    prior_scale: str = "auto"
    tolerance_length_mm: float | None = None
    tolerance_angle_deg: float | None = None
    tolerance_joint_offset_deg: float | None = None
    tolerance_tool_mm: float | None = None
    tolerance_tool_deg: float | None = None

    def __post_init__(self) -> None:
        for name in ("tolerance_length_mm", "tolerance_angle_deg", "tolerance_joint_offset_deg", "tolerance_tool_mm",
                     "tolerance_tool_deg"):
            if getattr(self, name) is not None:
                check_range(self, name, low=0.0, low_open=True)
        if str(self.prior_scale).lower() not in ("auto", "cv", "nominal"):
            try:
                scale = float(self.prior_scale)
            except ValueError:
                scale = -1.0
            if not math.isfinite(scale) or scale < 0:
                raise TorchcalError(f"prior_scale must be auto, cv, nominal or a number >= 0, got {self.prior_scale!r}")
        super().__post_init__()


@dataclass
class HeadOptions(_Checked):
    """The learned residual stage (:mod:`torchcal.stages.residual`).

    Attributes:
        residual: ``auto`` (cross-validate every candidate head on top of the chosen structure,
            keep one only where it beats it beyond noise), ``none``, or head names joined by ``+``.
        head_time_check: a head that passes the CV must pass again on contiguous blocks of the
            file's row order (measurement order), so that one that learned a drift is refused.
        residual_hidden: hidden units of ELM heads.
        residual_margin: a head must lower the CV RMS by this fraction (and with a paired gain
            beyond chance over configuration groups) to be kept.
    """

    residual: str = "auto"
    head_time_check: bool = True
    residual_hidden: int = 80
    residual_margin: float = 0.05

    def __post_init__(self) -> None:
        check_range(self, "residual_margin", low=0.0, high=1.0, high_open=True)
        # upper bound where memory or time would run away long before a better fit
        check_range(self, "residual_hidden", low=1, high=20000)
        super().__post_init__()


@dataclass
class SearchOptions(_Checked):
    """The Mayfly (MMA) search of the ELM heads' hidden layer (:mod:`torchcal.optimize`).

    Attributes:
        mayfly_population / mayfly_iterations: swarm size and iterations.
    """

    mayfly_population: int = 20
    mayfly_iterations: int = 50

    def __post_init__(self) -> None:
        # upper bounds where memory or time would run away long before a better fit
        check_range(self, "mayfly_population", low=1, high=10000)
        check_range(self, "mayfly_iterations", low=1, high=100000)
        super().__post_init__()


@dataclass
class UncertaintyOptions(_Checked):
    """The per-pose 95 % region reported for new poses (:mod:`torchcal.stages.prediction_uncertainty`).

    Attributes:
        uncertainty: ``conformal`` (default), ``gaussian`` (both calibrated on the out-of-fold errors
            of the fit's grouped cross-validation, which then runs even when nothing else is chosen)
            or ``none`` (no calibration, no extra fits).
    """

    uncertainty: str = "conformal"

    def __post_init__(self) -> None:
        if self.uncertainty not in ("conformal", "gaussian", "none"):
            raise TorchcalError(f"uncertainty must be 'conformal', 'gaussian' or 'none', got {self.uncertainty!r}")
        super().__post_init__()


@dataclass
class RuntimeOptions(_Checked):
    """Where and how a command runs.

    Attributes:
        device: ``cpu`` or a torch device string.
        progress: show progress of long steps.
        jobs: processes that fit a fit's independent pieces side by side (the heads of a
            cross-validation fold; :mod:`torchcal.core.workers`): ``null`` (default) = the
            ``TORCHCAL_JOBS`` environment variable, else the usable cores; ``1`` = this process only.
            The results are the same for every value.
    """

    device: str = "cpu"
    progress: bool = True
    jobs: int | None = None

    def __post_init__(self) -> None:
        if self.jobs is not None:
            check_range(self, "jobs", low=1, high=1024)
            if self.jobs != int(self.jobs):
                raise TorchcalError(f"jobs must be a whole number of processes, got {self.jobs!r}")
        super().__post_init__()


@dataclass
class FitConfig(RuntimeOptions, UncertaintyOptions, SearchOptions, HeadOptions, PriorOptions, ValidationOptions,
                StructureOptions, UnitOptions):
    """Options of ``torchcal fit`` on tracker points (and the fit stage of ``run``): the concerns
    above composed, their keys flat (``cv_folds=3``, ``residual=none``); each concern checks its
    own values before any file is read. Instruments with other needs compose the concerns they use
    (the stiffness fit: units and validation; the profile fit: units)."""


@dataclass
class RunConfig:
    """The main job: simulate the default twin, fit, evaluate on held-out poses, report, export.

    Attributes:
        name: run name, the folder under ``out`` (and under ``export_dir``).
        out: folder of the runs (report, model, metrics).
        twin: the twin the run simulates (:class:`~torchcal.sim.twin.TwinConfig`).
        fit: the fit's options (:class:`FitConfig`).
        export: export the compensator and check it with onnxruntime.
        export_dir: folder of the exported compensators.
    """

    name: str = "twin-default"
    out: str = "runs"
    twin: TwinConfig = field(default_factory=lambda: TwinConfig(gravity=True, gear=True, n_train=1500, n_test=600))
    fit: FitConfig = field(default_factory=FitConfig)
    export: bool = True
    export_dir: str = "exported_models"
