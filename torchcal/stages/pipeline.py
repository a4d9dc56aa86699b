"""The one fit pipeline of a geometry model: structure by cross-validation, model folder, residual stage.

``torchcal fit`` (every instrument whose points are TCP positions), ``torchcal run``, the
real-data validation and every study trial call :func:`fit_model`; what they do around it
(loading, the twin's truth, scoring) is theirs, the sequence is here once:

1. :func:`~torchcal.stages.geometry.fit_with_selection` (or a fit the caller already has),
2. :func:`~torchcal.stages.geometry.save_fit` with the fit's structure CV (prediction uncertainty),
3. the resolved options as ``config.yaml`` in the folder,
4. :func:`~torchcal.stages.residual.fit_residual_stage` unless ``residual=none``; with
   ``residual=none`` the structure comparison alone is written to ``model_selection.json``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torchcal.config.compose import save_resolved_config
from torchcal.config.workers import start_fit_workers
from torchcal.core.threads import fit_threads
from torchcal.core.workers import import_in_workers
from torchcal.data.measurements import Measurements
from torchcal.identify.calibrate import CalibrationResult
from torchcal.kinematics.robot import RobotModel
from torchcal.model_selection.compare import Comparison
from torchcal.model_selection.structure import StructureCV
from torchcal.stages.geometry import fit_with_selection, save_fit
from torchcal.stages.prior_options import prior_metadata
from torchcal.stages.residual import (
    ResidualOutcome,
    fit_residual_stage,
    head_modules,
    write_selection,
)

#: What the structure cross-validation's fold fits import (a worker imports it when it starts).

#: The decision recorded in ``model_selection.json`` when no head was asked for.
NO_HEADS = "residual=none: no head considered"


@dataclass
class FitRun:
    """What :func:`fit_model` produced.

    ``folder``: the model folder written; ``result``: the geometry (and joint-space) fit on all
    poses; ``structure``: its cross-validation (``None`` when there was nothing to choose);
    ``residual``: the residual stage's outcome (``None`` with ``residual=none``).
    """

    folder: Path
    result: CalibrationResult
    structure: StructureCV | None
    residual: ResidualOutcome | None

    @property
    def comparison(self) -> Comparison | None:
        """The final model-selection table: with heads when the residual stage ran, else the structures'."""
        if self.residual is not None:
            return self.residual.comparison
        return self.structure.comparison if self.structure is not None else None

    @property
    def head(self) -> str | None:
        """The residual head kept (``None``: none)."""
        return self.residual.kept if self.residual is not None else None

    def lines(self) -> list[str]:
        """What a command prints about the fit: identifiability, then the selection table and decision."""
        lines = [self.result.identifiability.summary()]
        if self.result.prior_selection is not None and self.result.prior is not None:
            lines += [(f"prior: {self.result.prior.spec.describe()}; strength chosen by "
                       f"{self.result.prior_selection['protocol']}:"),
                      self.result.prior_selection["table"]]
        prior = prior_metadata(self.result)
        if prior is not None:
            lines.append(prior["summary"])
        if self.residual is not None:
            lines += [self.residual.table, self.residual.decision]
        elif self.structure is not None and self.structure.comparison is not None:
            lines.append(self.structure.comparison.format_table())
        return lines


def fit_model(
    folder: str | Path,
    robot: RobotModel,
    data: Measurements,
    config: Any,
    *,
    metadata: dict | Callable[[CalibrationResult], dict] | None = None,
    fitted: tuple[CalibrationResult, StructureCV | None] | None = None,
    progress: Callable[[str], None] | None = None,
    residual_progress: Callable[[str], None] | None = None,
) -> FitRun:
    """Fit ``robot`` to ``data`` with the options ``config`` (a ``FitConfig``) and write the model folder.

    ``metadata``: extra entries of ``calibration.json`` (or a function of the fit result giving
    them, for entries computed from it); ``fitted``: the ``(result, structure)`` of
    :func:`fit_with_selection` already computed on ``data`` with these options (a study reuses it
    across trials that differ only in their heads); ``progress(text)``: called before long steps;
    ``residual_progress``: the residual stage's per-fold lines (default ``progress``). Runs on
    :data:`~torchcal.core.threads.FIT_THREADS` torch threads (:mod:`torchcal.core.threads`).
    """
    with fit_threads():
        return _fit_model(Path(folder), robot, data, config, metadata, fitted, progress, residual_progress)


def _fit_model(folder: Path, robot: RobotModel, data: Measurements, config: Any, metadata, fitted, progress,
               residual_progress) -> FitRun:
    start_fit_workers(config)  # their start-up overlaps the fit's serial part (core.workers)
    result, structure = fitted if fitted is not None else fit_with_selection(robot, data, config, progress=progress)
    if config.residual != "none":
        import_in_workers(head_modules(config))  # imported there while the model folder is written
    extra = metadata(result) if callable(metadata) else dict(metadata or {})
    folder = save_fit(Path(folder), robot, data, result, extra, structure=structure, uncertainty=config.uncertainty)
    save_resolved_config(folder / "config.yaml", config)
    residual = None
    if config.residual != "none":
        if progress is not None:
            progress("cross-validating residual heads")
        residual = fit_residual_stage(folder, data, config, progress=residual_progress or progress, structure=structure)
    elif structure is not None and structure.comparison is not None:
        write_selection(folder, structure.comparison, NO_HEADS)
    return FitRun(folder, result, structure, residual)
