"""Calibration without a measuring instrument: a ball on the flange put into fixture sockets.

A file ``placement, socket, q1..qN`` lists joint configurations that put the ball centre into the
same (unknown) socket point; the two sockets of one fixture placement are a known distance apart
(the scale). ``fit`` identifies what those constraints can see (:mod:`torchcal.instruments.sockets.fit`);
``evaluate`` scores consistency and distortion on other placements.

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


class SocketsInstrument(Instrument):
    """Socket (fixed-point) constraints with a two-socket scale; the robot's encoders are the only sensor."""

    name: ClassVar[str] = "sockets"
    description: ClassVar[str] = "ball in two-socket fixtures (sockets.csv, sockets_test.csv)"
    stage: ClassVar[str] = "geometry"
    required_columns: ClassVar[frozenset[str]] = frozenset({"placement", "socket"})

    def load(self, path: Path, robot: Any, overrides: list[str] | None = None) -> Any:
        from torchcal.instruments.sockets.commands import sockets_config
        from torchcal.instruments.sockets.data import load_socket_data

        config = sockets_config(overrides or [])
        return load_socket_data(path, robot, joint_unit=config.joint_unit, check_limits=config.check_limits)

    def fit(self, request: FitRequest) -> FitOutcome:
        from torchcal.instruments.sockets.commands import fit_sockets

        return fit_sockets(request.robot, request.data, request.out, request.overrides,
                           base_link=request.base_link, end_link=request.end_link, progress=request.progress)

    def evaluate(self, request: EvaluateRequest) -> EvaluateOutcome:
        from torchcal.instruments.sockets.commands import evaluate_sockets

        return EvaluateOutcome(evaluate_sockets(request.model, request.data, request.overrides, register=request.register))

    def options(self) -> type:
        from torchcal.instruments.sockets.commands import SocketsFitConfig

        return SocketsFitConfig

    def evaluate_options(self) -> tuple[str, ...]:
        return ("joint_unit", "check_limits", "placements", "distance_mm")

    def twin(self) -> TwinSpec:
        from torchcal.instruments.sockets.twin import SocketsTwinConfig, write_sockets_case

        return TwinSpec(SocketsTwinConfig, write_sockets_case, self.description)

    def contract_case(self) -> ContractCase:
        # encoder noise 0.001 deg per joint moves the ball by about 15 um at arm's length: a correct
        # fit leaves consistency near that on new placements; the nominal twin misses by about 1 mm
        return ContractCase(
            twin_overrides=["configurations_per_socket=30"],
            fit_file="sockets.csv",
            test_file="sockets_test.csv",
            metric="consistency_mean_mm",
            bound=0.05,
        )
