"""The multi-station laser tracer: lengths ``l1..lM`` from stations at unknown places.

``fit`` identifies the robot, the stations and their dead paths from lengths alone
(:mod:`torchcal.instruments.tracer.commands`); ``evaluate`` on a length file re-fits only the
stations (a new set-up) and scores the lengths. A file with ``l1`` alone is one station (a
draw-wire at an unknown anchor): :mod:`torchcal.instruments.tracer.one_station` fits what one
length per pose can support, chosen by order-blocked cross-validation.
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


def _one_station(path: Path) -> bool:
    """Whether the length file at ``path`` has a single station (``l1`` and no ``l2``)."""
    from torchcal.data.csv_table import read_header

    return "l2" not in read_header(path)


class TracerInstrument(Instrument):
    """Laser-tracer lengths; stations and dead paths are fitted with the robot."""

    name: ClassVar[str] = "tracer"
    description: ClassVar[str] = "multi-station laser-tracer lengths (lengths.csv, test.csv)"
    stage: ClassVar[str] = "geometry"
    required_columns: ClassVar[frozenset[str]] = frozenset({"l1"})

    def load(self, path: Path, robot: Any, overrides: list[str] | None = None) -> Any:
        from torchcal.instruments.tracer.commands import tracer_config
        from torchcal.instruments.tracer.data import load_tracer_data

        config = tracer_config(overrides or [])
        if _one_station(path):
            from torchcal.instruments.tracer.one_station.data import load_length_data

            return load_length_data(path, robot, joint_unit=config.joint_unit, length_unit=config.length_unit,
                                    check_limits=config.check_limits)
        return load_tracer_data(path, robot, joint_unit=config.joint_unit, length_unit=config.length_unit,
                                triangle_tolerance_mm=config.triangle_tolerance_mm)

    def fit(self, request: FitRequest) -> FitOutcome:
        from torchcal.instruments.tracer.commands import fit_tracer

        if _one_station(request.data):
            from torchcal.instruments.tracer.one_station.commands import fit_length_station

            return fit_length_station(request.robot, request.data, request.out, request.overrides,
                                      base_link=request.base_link, end_link=request.end_link, progress=request.progress)
        return fit_tracer(request.robot, request.data, request.out, request.overrides,
                          base_link=request.base_link, end_link=request.end_link, progress=request.progress)

    def evaluate(self, request: EvaluateRequest) -> EvaluateOutcome:
        from torchcal.instruments.tracer.commands import evaluate_tracer

        if _one_station(request.data):
            from torchcal.instruments.tracer.one_station.commands import evaluate_length_station

            return EvaluateOutcome(evaluate_length_station(request.model, request.data, request.overrides,
                                                           register=request.register))
        return EvaluateOutcome(evaluate_tracer(request.model, request.data, request.overrides, register=request.register))

    def options(self) -> type:
        from torchcal.instruments.tracer.commands import TracerFitConfig

        return TracerFitConfig

    def evaluate_options(self) -> tuple[str, ...]:
        # a length-station file reads check_limits and refit_anchor, a tracer file the sigmas and triangle_tolerance_mm
        return ("joint_unit", "length_unit", "check_limits", "max_iterations", "sigma_constant_um", "sigma_per_m_um",
                "triangle_tolerance_mm",
                "refit_anchor")

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
