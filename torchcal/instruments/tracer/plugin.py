"""The multi-station laser tracer: lengths ``l1..lM`` from stations at unknown places.

``fit`` identifies the robot, the stations and their dead paths from lengths alone
(:mod:`torchcal.instruments.tracer.commands`); ``evaluate`` on a length file re-fits only the
stations (a new set-up) and scores the lengths. A file with ``l1`` alone is one station (a
draw-wire at an unknown anchor), the instrument ``length_station``
(:mod:`torchcal.instruments.tracer.one_station`), which shares this package's length model.

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


class TracerInstrument(Instrument):
    """Laser-tracer lengths; stations and dead paths are fitted with the robot."""

    name: ClassVar[str] = "tracer"
    description: ClassVar[str] = "multi-station laser-tracer lengths (lengths.csv, test.csv)"
    stage: ClassVar[str] = "geometry"
    required_columns: ClassVar[frozenset[str]] = frozenset({"l1", "l2"})

    def load(self, path: Path, robot: Any, overrides: list[str] | None = None) -> Any:
        from torchcal.instruments.tracer.commands import tracer_config
        from torchcal.instruments.tracer.data import load_tracer_data

        config = tracer_config(overrides or [])
        return load_tracer_data(path, robot, joint_unit=config.joint_unit, length_unit=config.length_unit,
                                triangle_tolerance_mm=config.triangle_tolerance_mm)

    def fit(self, request: FitRequest) -> FitOutcome:
        from torchcal.instruments.tracer.commands import fit_tracer

        return fit_tracer(request.robot, request.data, request.out, request.overrides,
                          base_link=request.base_link, end_link=request.end_link, progress=request.progress)

    def evaluate(self, request: EvaluateRequest) -> EvaluateOutcome:
        from torchcal.instruments.tracer.commands import evaluate_tracer

        return EvaluateOutcome(evaluate_tracer(request.model, request.data, request.overrides, register=request.register))

    def options(self) -> type:
        from torchcal.instruments.tracer.commands import TracerFitConfig

        return TracerFitConfig

    def evaluate_options(self) -> tuple[str, ...]:
        return ("joint_unit", "length_unit", "max_iterations", "sigma_constant_um", "sigma_per_m_um",
                "triangle_tolerance_mm")

    def twin(self) -> TwinSpec:
        from torchcal.instruments.tracer.twin_case import TracerTwinConfig, write_tracer_case

        return TwinSpec(TracerTwinConfig, write_tracer_case, self.description)

    def contract_case(self) -> ContractCase:
        # 60 poses from 4 stations: the tracker-measured test poses, registered, sit near their
        # own noise (test_sigma_mm per axis); the nominal robot misses by about 1 mm.
        return ContractCase(
            twin_overrides=["n_train=60", "n_test=100"],
            fit_file="lengths.csv",
            test_file="test.csv",
            metric="position_rms_mm",
            bound=0.06,
            register=True,
        )
