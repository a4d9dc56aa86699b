"""The laser tracker: 3-D TCP points ``x, y, z`` in the tracker's own (unknown, rigid) frame.

``fit`` identifies the robot's geometry (structure chosen by grouped cross-validation, see
:func:`~torchcal.stages.geometry.fit_with_selection`) and, unless ``residual=none``, a learned
residual head kept only where it helps on new poses (:mod:`torchcal.stages.residual`).
"""

from __future__ import annotations

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

    def load(self, path: Path, robot: Any, overrides: list[str] | None = None) -> Any:
        from torchcal.config.compose import compose_fit_config
        from torchcal.data.measurements import load_measurements

        config = compose_fit_config(overrides or [])
        return load_measurements(path, robot, joint_unit=config.joint_unit, length_unit=config.length_unit)

    def fit(self, request: FitRequest) -> FitOutcome:
        from torchcal.config import save_resolved_config
        from torchcal.config.compose import compose_fit_config
        from torchcal.core.metrics import position_metrics
        from torchcal.identify.joint_fit import predicted_positions
        from torchcal.kinematics.robot import load_robot
        from torchcal.stages.geometry import (
            describe_structure,
            fit_with_selection,
            nominal_errors,
            save_fit,
            with_tool,
        )
        from torchcal.stages.residual import fit_residual_stage, write_selection

        config = compose_fit_config(request.overrides)
        robot = with_tool(load_robot(request.robot, base_link=request.base_link, end_link=request.end_link), config)
        data = self.load(request.data, robot, request.overrides)
        request.progress(f"identifying {robot.name} from {len(data)} poses")
        result, structure = fit_with_selection(robot, data, config, progress=request.progress)
        before = position_metrics(nominal_errors(robot, data))
        after = position_metrics(data.position - predicted_positions(result, data.q))
        folder = save_fit(request.out, robot, data, result,
                          {"fit_metrics": {"nominal_registered": before, "geometric": after}},
                          structure=structure, uncertainty=config.uncertainty)
        save_resolved_config(folder / "config.yaml", config)
        lines = [result.identifiability.summary(),
                 (f"training RMS {before['position_rms_mm']:.4f} mm (nominal, registered) -> "
                  f"{after['position_rms_mm']:.4f} mm ({describe_structure(result)}, on the poses it was fitted to)")]
        if config.residual != "none":
            request.progress("cross-validating residual heads")
            summary = fit_residual_stage(folder, data, config, progress=request.progress, structure=structure)
            lines += [summary["table"], summary["decision"]]
        elif structure is not None:
            write_selection(folder, structure.comparison, "residual=none: no head considered")
            lines.append(structure.comparison.format_table())
        return FitOutcome(folder=folder, lines=lines)

    def evaluate(self, request: EvaluateRequest) -> EvaluateOutcome:
        from torchcal.config.schema import FitConfig
        from torchcal.core.overrides import apply_overrides
        from torchcal.instruments.tracker.evaluate import evaluate
        from torchcal.model_selection.leakage import LeakageReport

        config = apply_overrides(FitConfig(), request.overrides)
        metrics = evaluate(request.model, request.data, register=request.register, config=config)
        lines = []
        if "leakage" in metrics:
            report = LeakageReport(**metrics["leakage"])
            lines.append(f"{'warning: ' if report.warning else ''}{report.summary()}")
        if "uncertainty" in metrics:
            u = metrics["uncertainty"]
            lines.append(f"predicted 95 % error radius ({u['method']}, from the fit's grouped cross-validation) covers "
                         f"{100 * u['coverage_95']:.1f} % of these poses; predicted p95 {u['predicted_p95_mm']:.4f} mm, "
                         f"observed {u['observed_p95_mm']:.4f} mm")
        comp = metrics["compensator"]
        lines.append(
            f"the exported compensator ({comp['task']} first, {comp['iterations']} steps) solves "
            f"{100 * comp['solved_share']:.1f} % of these poses to 1 um (worst {comp['unsolved_max_mm']:.2e} mm); "
            f"tool orientation deviation median {comp['orientation_deviation_median_rad']:.1e} rad, "
            f"max {comp['orientation_deviation_max_rad']:.1e} rad")
        return EvaluateOutcome(metrics=metrics, lines=lines)

    def options(self) -> type:
        from torchcal.config.schema import FitConfig

        return FitConfig

    def twin(self) -> TwinSpec:
        from torchcal.sim.twin import TwinConfig, write_twin_case

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
