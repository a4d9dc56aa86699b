"""The laser tracker: 3-D TCP points ``x, y, z`` in the tracker's own (unknown, rigid) frame.

``fit`` identifies the robot's geometry (structure chosen by grouped cross-validation, see
:func:`~torchcal.stages.geometry.fit_with_selection`) and, unless ``residual=none``, a learned
residual head kept only where it helps on new poses (:mod:`torchcal.stages.residual`).

Its methods import what they use when they run: the registry imports every plugin to list and
recognise instruments (``--help``, a file's header), which must stay cheap.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any, ClassVar

from torchcal.instruments.base import (
    ContractCase,
    EvaluateOutcome,
    EvaluateRequest,
    FitOutcome,
    FitRequest,
    Instrument,
    TwinSpec,
)


class TrackerInstrument(Instrument):
    """Laser-tracker points; the instrument frame is fitted with the robot (6 parameters)."""

    name: ClassVar[str] = "tracker"
    description: ClassVar[str] = "laser-tracker points (train.csv, test.csv)"
    stage: ClassVar[str] = "geometry"
    required_columns: ClassVar[frozenset[str]] = frozenset({"x", "y", "z"})
    multi_series: ClassVar[bool] = True

    def load(self, path: Path, robot: Any, overrides: list[str] | None = None) -> Any:
        from torchcal.config.compose import compose_fit_config
        from torchcal.data.measurements import load_measurements

        config = compose_fit_config(overrides or [])
        return load_measurements(path, robot, joint_unit=config.joint_unit, length_unit=config.length_unit)

    def fit(self, request: FitRequest) -> FitOutcome:
        from torchcal.config.compose import compose_fit_config
        from torchcal.config.workers import start_fit_workers

        config = compose_fit_config(request.overrides)
        # before this process imports torch: their start-up overlaps it and the files' reading
        start_fit_workers(config)

        from torchcal.core.workers import import_while_waiting
        from torchcal.instruments.tracker.report import REPORT_MODULES

        import_while_waiting(*REPORT_MODULES)  # the report's, in a wait for the workers during the fit

        from torchcal.core.metrics import position_metrics
        from torchcal.identify.joint_fit import predicted_positions
        from torchcal.kinematics.robot import load_robot
        from torchcal.stages.geometry import NOMINAL_PROTOCOL, nominal_errors, with_tool
        from torchcal.stages.pipeline import fit_model
        robot = with_tool(load_robot(request.robot, base_link=request.base_link, end_link=request.end_link), config)
        files = (request.data, *request.more_data)
        series, set_aside = [], {}
        for file in files:
            data, aside = self._checked(file, robot, request, config)
            series.append(data)
            if aside:
                set_aside[str(file)] = aside
        if len(files) == 1:
            set_aside = set_aside.get(str(request.data), {})

        def fit_metrics(result: Any, nominal=None) -> dict:
            before = position_metrics(nominal if nominal is not None else nominal_errors(robot, data))
            after = position_metrics(data.position - predicted_positions(result, data.q))
            return {"fit_metrics": {"protocol": f"training poses, optimistic; nominal: {NOMINAL_PROTOCOL}",
                                    "nominal": before, "geometry_stage": after}, **set_aside}

        if len(series) == 1:
            request.progress(f"identifying {robot.name} from {len(data)} poses")
            run = fit_model(request.out, robot, data, config, metadata=fit_metrics, progress=request.progress)
        else:
            import torch

            from torchcal.stages.series import fit_series, series_metadata

            request.progress(f"identifying {robot.name} from {len(series)} series ({sum(map(len, series))} poses)")
            fitted = fit_series(robot, series, config, progress=request.progress)
            data = fitted.pooled  # every series in the first one's frame (what the folder and the heads see)
            nominal = torch.cat([nominal_errors(robot, s) for s in series])  # each series with its own frame and tool
            run = fit_model(request.out, robot, data, config, fitted=(fitted.result, fitted.structure),
                            metadata=lambda result: {**fit_metrics(result, nominal), **series_metadata(series, fitted)},
                            progress=request.progress)
        lines = run.lines()
        request.progress("writing the report")
        lines.append(_write_fit_report(run.folder, data, run.structure, lines, config))
        return FitOutcome(folder=run.folder, lines=lines, report=run.folder / "report.md")

    def _checked(self, file: Path, robot: Any, request: FitRequest, config: Any) -> tuple[Any, dict]:
        """One file loaded, its rows the geometry cannot explain set aside; returns the poses and what was set aside."""
        from torchcal.identify.outliers import (
            check_orientation_columns,
            find_orientation_outlier_rows,
            find_outlier_rows,
        )

        data = self.load(file, robot, request.overrides)
        still = still_joints(data, robot.joint_names)
        for line in still:
            warnings.warn(f"{file}: {line}", stacklevel=3)
        request.progress(f"checking {len(data)} poses for rows the geometry cannot explain")
        outliers = find_outlier_rows(robot, data, parallel_threshold_deg=config.parallel_threshold_deg)
        check_orientation_columns(robot, data, parallel_threshold_deg=config.parallel_threshold_deg)
        set_aside: dict = {"joints_not_moved": still} if still else {}
        if outliers is not None:
            warnings.warn(outliers.message(str(file)), stacklevel=3)
            data = data.subset([i for i in range(len(data)) if i not in set(outliers.index)])
            set_aside["rows_left_out"] = {"file_lines": list(outliers.lines), "errors_mm": list(outliers.errors_mm),
                                           "median_mm_of_the_others": outliers.median_mm}
        turned = find_orientation_outlier_rows(robot, data, parallel_threshold_deg=config.parallel_threshold_deg)
        if turned is not None:
            warnings.warn(turned.message(str(file)), stacklevel=3)
            data = data.subset([i for i in range(len(data)) if i not in set(turned.index)])
            set_aside["orientation_rows_left_out"] = {"file_lines": list(turned.lines), "angles_deg": list(turned.angles_deg),
                                                      "median_deg_of_the_others": turned.median_deg}
        return data, set_aside

    def evaluate(self, request: EvaluateRequest) -> EvaluateOutcome:
        from torchcal.config.compose import compose_options
        from torchcal.config.schema import FitConfig
        from torchcal.data.measurements import load_measurements
        from torchcal.instruments.tracker.evaluate import score
        from torchcal.model_selection.leakage import LeakageReport
        from torchcal.stages.store import load_model

        config = compose_options(FitConfig(), request.overrides)
        stored = load_model(request.model)
        data = load_measurements(request.data, stored.robot, joint_unit=config.joint_unit, length_unit=config.length_unit)
        scored = score(stored, data, register=request.register)
        metrics = scored.metrics
        lines = [(f"{len(data)} poses: the model misses them by {metrics['position_rms_mm']:.4f} mm RMS, the nominal robot "
                  f"by {metrics['nominal_position_rms_mm']:.4f} mm ({metrics['nominal']['protocol']})")]
        if "orientation" in metrics:
            o = metrics["orientation"]
            lines.append(f"tool orientation (rx, ry, rz): the model misses it by {o['orientation_rms_deg']:.4f} deg RMS "
                         f"({o['protocol']}), the nominal robot by {o['nominal']['orientation_rms_deg']:.4f} deg "
                         f"({o['nominal']['protocol']})")
        if "leakage" in metrics:
            leakage = LeakageReport(**metrics["leakage"])
            lines.append(f"{'warning: ' if leakage.warning else ''}{leakage.summary()}")
        if "uncertainty" in metrics:
            u = metrics["uncertainty"]
            split = ""
            if u.get("n_far"):
                like = u.get("coverage_95_like_training")
                split = (f" ({100 * u['coverage_95_far']:.1f} % of the {u['n_far']} further than {u['far_radius_mm']:.0f} mm "
                         "from every training pose, where the model extrapolates and the radius promises nothing"
                         + (f"; {100 * like:.1f} % of the others" if like is not None else "") + ")")
            lines.append(f"predicted 95 % error radius ({u['protocol']}) covers {100 * u['coverage_95']:.1f} % of these "
                         f"poses{split}; predicted p95 {u['predicted_p95_mm']:.4f} mm, observed {u['observed_p95_mm']:.4f} mm")
        comp = metrics["compensator"]
        lines.append(
            f"the exported compensator ({comp['task']} first, {comp['iterations']} steps) solves "
            f"{100 * comp['solved_share']:.1f} % of these poses to 1 um (worst {comp['unsolved_max_mm']:.2e} mm); "
            f"tool orientation deviation median {comp['orientation_deviation_median_rad']:.1e} rad, "
            f"max {comp['orientation_deviation_max_rad']:.1e} rad" + _corrections_text(comp))
        report = None
        if request.report is not None:
            report = _write_evaluate_report(Path(request.report), scored, request.register, lines)
        return EvaluateOutcome(metrics=metrics, lines=lines, report=report)

    def shown_metrics(self, metrics: dict) -> dict:
        # the point figures; leakage, uncertainty and the compensator are in the lines printed above
        return {k: v for k, v in metrics.items()
                if k.startswith(("n_", "position_", "nominal_position_", "orientation_", "nominal_orientation_"))}

    def options(self) -> type:
        from torchcal.config.schema import FitConfig

        return FitConfig

    def evaluate_options(self) -> tuple[str, ...]:
        return ("joint_unit", "length_unit")

    def run(self, config: Any, console: Any = None) -> dict:
        from torchcal.instruments.tracker.run import run

        return run(config, console=console)

    def twin(self) -> TwinSpec:
        from torchcal.instruments.tracker.twin_case import write_twin_case
        from torchcal.sim.twin import TwinConfig

        return TwinSpec(TwinConfig, write_twin_case, self.description)

    def contract_case(self) -> ContractCase:
        # Geometry only on 120 poses: the held-out RMS sits near the noise floor sqrt(3 (12^2 + 8^2)) um
        # = 25 um; the nominal robot misses by about 1 mm.
        return ContractCase(
            twin_overrides=["n_train=120", "n_test=200"],
            fit_file="train.csv",
            test_file="test.csv",
            fit_overrides=["residual=none", "gravity_compliance=none", "joint_harmonics=none"],
            metric="position_rms_mm",
            bound=0.05,
        )


#: A joint whose angles span less than this (deg) in a file is taken as not moving.
STILL_JOINT_DEG = 1.0


def still_joints(data: Any, joint_names: tuple[str, ...]) -> list[str]:
    """One line per joint that (nearly) never moves in ``data``: what a model says elsewhere is extrapolation."""
    q_deg = data.q.detach().cpu().double() * (180.0 / math.pi)
    span = q_deg.max(dim=0).values - q_deg.min(dim=0).values
    return [f"{name} (q{j + 1}) spans only {float(span[j]):.3f} deg in this file (around {float(q_deg[:, j].median()):.2f} "
            f"deg): its parameters are seen at that angle only, and what the model predicts at other {name} "
            "angles is extrapolation; measure poses that move it"
            for j, name in enumerate(joint_names) if float(span[j]) < STILL_JOINT_DEG]


def _selection(folder: Path) -> dict | None:
    """The folder's ``model_selection.json``, if the fit made choices."""
    import json

    path = Path(folder) / "model_selection.json"
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None


def _write_fit_report(folder: Path, data: Any, structure: Any, lines: list[str], config: Any) -> str:
    """Write the fit's report into its folder; returns the console line that sums the model up."""
    from torchcal.core.metrics import position_metrics
    from torchcal.core.workers import resolve_jobs
    from torchcal.instruments.tracker.evaluate import score
    from torchcal.instruments.tracker.report import (
        ReportInputs,
        calibration_report,
        cross_validated_stage,
        model_name,
        score_pose_set,
    )
    from torchcal.report.document import write_report
    from torchcal.stages.store import load_model

    stored = load_model(folder)
    scored = score(stored, data, leakage=False, corrections=False)
    cv = cross_validated_stage(stored, structure)
    extra = [cv] if cv is not None else []
    cv_text = "" if cv is None else (f"; cross-validated {position_metrics(cv.errors_m)['position_rms_mm']:.4f} mm "
                                     f"({structure.folds.k}-fold, held out)")
    chosen_by = "set by the options (nothing to choose)"
    if structure is not None and len(structure.options) > 1:
        chosen_by = f"chosen by {structure.folds.label}"
    selection = _selection(folder) or {}
    kept = next((row for row in selection.get("candidates", []) if row.get("name") == selection.get("chosen")), None)
    if stored.residual is not None and kept is not None and structure is not None:
        # the kept head's own row: the structure's out-of-fold figure is not the model's
        cv_text = (f"; cross-validated {kept['cv_rms_mm']:.4f} mm ({selection['chosen']}, {structure.folds.k}-fold, "
                   "held out)")
        chosen_by += f", the head kept by {structure.folds.label}"
    pose_set = score_pose_set(stored, data, held_out=False, extra=extra, focus_extra=bool(extra))
    figures = [f"{position_metrics(s.errors_m)['position_rms_mm']:.4f} mm ({s.name})" for s in pose_set.stages
               if not s.name.endswith("cross-validated")]
    head = f"; residual head: {stored.residual.head.name}" if stored.residual is not None else ""
    summary = (f"calibrated model: {model_name(stored)}, structure {chosen_by}{head}. Training RMS "
               + " -> ".join(figures) + f" on the {len(data)} poses it was fitted to (optimistic; nominal: instrument "
               f"frame and tool fitted){cv_text}")
    report = calibration_report(
        f"Calibration report: {stored.robot.name}, fit on {Path(data.source).name}", stored, [pose_set],
        ReportInputs(selection=_selection(folder), compensator=scored.metrics["compensator"],
                     uncertainty=scored.metrics.get("uncertainty"), lines=[*lines, summary]),
        jobs=resolve_jobs(config.jobs))  # the fit's worker is idle now: it draws every other figure
    write_report(folder, report, member=True)
    return summary


def _write_evaluate_report(target: Path, scored: Any, register: bool, lines: list[str]) -> Path:
    """Write the report of an evaluation into ``target``; returns the path of its ``report.md``."""
    from torchcal.instruments.tracker.report import ReportInputs, calibration_report, score_pose_set
    from torchcal.report.document import write_report

    stored, data = scored.stored, scored.data
    fitted = (stored.metadata.get("data") or {}).get("sha256") == data.sha256
    leakage = scored.metrics.get("leakage") or {}
    protocol = None
    if not fitted and leakage.get("warning"):
        protocol = (f"file {Path(data.source).name}, not the fitted file, but its poses sit among the training poses "
                    f"({100 * leakage['twin_share']:.0f} % training twins; see the leakage note): optimistic")
    pose_set = score_pose_set(stored, data, held_out=not fitted, register=register, protocol=protocol, scored=scored)
    report = calibration_report(
        f"Evaluation report: {stored.robot.name}, model {stored.folder.name} on {Path(data.source).name}", stored,
        [pose_set], ReportInputs(selection=_selection(stored.folder), compensator=scored.metrics["compensator"],
                                 uncertainty=scored.metrics.get("uncertainty"), leakage=scored.metrics.get("leakage"),
                                 lines=lines))
    paths = write_report(target, report)
    return paths["report.md"]


def _corrections_text(comp: dict) -> str:
    """``; joint corrections up to ...`` of an evaluation's compensator summary (empty without them)."""
    c = comp.get("corrections")
    if not c or c["largest_joint_correction_sigma_deg"] is None:
        return ""
    return (f"; its joint corrections (poses not near a singularity) up to {c['largest_joint_correction_deg']:.3g} deg "
            f"(joint {c['joint']}; 1-sigma {c['largest_joint_correction_sigma_deg']:.2g} deg from the calibration's "
            f"uncertainty), median {c['median_joint_correction_deg']:.3g} deg")
