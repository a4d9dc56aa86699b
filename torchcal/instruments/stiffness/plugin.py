"""Stiffness from wrench/deflection pairs: ``fx..tz`` applied, ``dx, dy, dz`` (and rotations) measured.

``fit`` chooses the parameterization (classic joint springs or the full virtual-joint model) by
grouped cross-validation and identifies the compliances (:mod:`torchcal.instruments.stiffness.commands`).

Its methods import what they use when they run: the registry imports every plugin to list and
recognise instruments (``--help``, a file's header), which must stay cheap.
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


class StiffnessInstrument(Instrument):
    """A loading rig: wrenches at the tool and the deflections they cause."""

    name: ClassVar[str] = "stiffness"
    description: ClassVar[str] = (
        "loading rig (robot.yaml, stiffness_train.csv, stiffness_test.csv, stiffness_truth.json)")
    stage: ClassVar[str] = "stiffness"
    required_columns: ClassVar[frozenset[str]] = frozenset(
        {"fx", "fy", "fz", "tx", "ty", "tz", "dx", "dy", "dz"})

    def load(self, path: Path, robot: Any, overrides: list[str] | None = None) -> Any:
        from torchcal.instruments.stiffness.commands import load_stiffness_file, stiffness_config

        return load_stiffness_file(path, robot.dof, stiffness_config(overrides or []))

    def fit(self, request: FitRequest) -> FitOutcome:
        from torchcal.instruments.stiffness.commands import fit_stiffness

        return fit_stiffness(request.robot, request.data, request.out, request.overrides,
                             base_link=request.base_link, end_link=request.end_link, progress=request.progress)

    def evaluate(self, request: EvaluateRequest) -> EvaluateOutcome:
        from torchcal.instruments.stiffness.commands import evaluate_stiffness

        return EvaluateOutcome(evaluate_stiffness(request.model, request.data, request.overrides, register=request.register))

    def options(self) -> type:
        from torchcal.instruments.stiffness.commands import StiffnessFitConfig

        return StiffnessFitConfig

    def evaluate_options(self) -> tuple[str, ...]:
        return ("joint_unit", "length_unit", "device", "check_plausible")

    def twin(self) -> TwinSpec:
        from torchcal.instruments.stiffness.twin_case import (
            StiffnessCaseConfig,
            write_stiffness_twin_case,
        )

        return TwinSpec(StiffnessCaseConfig, write_stiffness_twin_case, self.description)

    def contract_case(self) -> ContractCase:
        # deflection noise 12 um per axis: a correct stiffness model leaves about that on new loads
        return ContractCase(
            twin_overrides=["n_train=60", "n_test=60"],
            fit_file="stiffness_train.csv",
            test_file="stiffness_test.csv",
            fit_overrides=["parameters=classic"],
            metric="deflection_rms_mm",
            bound=0.03,
        )
