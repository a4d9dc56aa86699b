"""One length station (a draw-wire, or one tracer station alone): ``q1..qN, l1``.

An instrument of its own: a file with ``l1`` and no ``l2`` is recognised here, not by the
multi-station tracer. It lives beside the tracer because it shares the tracer's length model and
its joint problem with one station (``l = |P(q) - A| + c``); what one length per pose can support
is chosen by order-blocked cross-validation (:mod:`torchcal.instruments.tracer.one_station.cv`).

The handlers are imported inside the methods, as in every plugin: ``torchcal --help`` reads the
registry without importing torch.
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


class LengthStationInstrument(Instrument):
    """One length sensor from an unknown anchor to the flange; anchor, offset and attachment are fitted."""

    name: ClassVar[str] = "length_station"
    description: ClassVar[str] = "one length station, e.g. a draw-wire (lengths.csv with l1 alone)"
    stage: ClassVar[str] = "geometry"
    required_columns: ClassVar[frozenset[str]] = frozenset({"l1"})

    def recognises(self, columns: set[str]) -> bool:
        """``l1`` without ``l2``: a second length column makes a multi-station tracer file."""
        return "l1" in columns and "l2" not in columns

    def load(self, path: Path, robot: Any, overrides: list[str] | None = None) -> Any:
        from torchcal.instruments.tracer.one_station.commands import length_station_config
        from torchcal.instruments.tracer.one_station.data import load_length_data

        config = length_station_config(overrides or [])
        return load_length_data(path, robot, joint_unit=config.joint_unit, length_unit=config.length_unit,
                                check_limits=config.check_limits)

    def fit(self, request: FitRequest) -> FitOutcome:
        from torchcal.instruments.tracer.one_station.commands import fit_length_station

        return fit_length_station(request.robot, request.data, request.out, request.overrides,
                                  base_link=request.base_link, end_link=request.end_link, progress=request.progress)

    def evaluate(self, request: EvaluateRequest) -> EvaluateOutcome:
        from torchcal.instruments.tracer.one_station.commands import evaluate_length_station

        return EvaluateOutcome(evaluate_length_station(request.model, request.data, request.overrides,
                                                       register=request.register))

    def options(self) -> type:
        from torchcal.instruments.tracer.one_station.commands import LengthStationConfig

        return LengthStationConfig

    def evaluate_options(self) -> tuple[str, ...]:
        return ("joint_unit", "length_unit", "check_limits", "max_iterations", "refit_anchor")

    def twin(self) -> TwinSpec:
        from torchcal.instruments.tracer.one_station.twin import (
            LengthStationTwinConfig,
            write_length_station_case,
        )

        return TwinSpec(LengthStationTwinConfig, write_length_station_case, self.description)

    def contract_case(self) -> ContractCase:
        # 0.01 mm reading noise: a correct fit leaves about that (0.011 mm measured) on the held-out lengths (anchor and
        # offset re-fitted, as for a new set-up); the nominal robot misses by several tenths of a mm
        return ContractCase(
            twin_overrides=["n_train=120", "n_test=60"],
            fit_file="lengths.csv",
            test_file="test.csv",
            metric="length_rms_mm",
            bound=0.03,
        )
