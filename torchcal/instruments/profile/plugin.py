"""A 2-D line-laser profile sensor on the flange, scanning a plane: ``scan, u, w`` per point.

``fit`` finds the sensor's mounting on the flange (hand-eye extrinsics) from profiles of one
plane seen from many poses (:mod:`torchcal.instruments.profile.commands`).

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


class ProfileInstrument(Instrument):
    """Line-laser profiles of a plane target; the sensor mounting is the fitted stage."""

    name: ClassVar[str] = "profile"
    description: ClassVar[str] = "line-laser profile sensor on a plane target (profile.csv)"
    stage: ClassVar[str] = "sensor"
    required_columns: ClassVar[frozenset[str]] = frozenset({"scan", "u", "w"})

    def load(self, path: Path, robot: Any, overrides: list[str] | None = None) -> Any:
        from torchcal.instruments.profile.commands import load_profile_file, profile_config

        return load_profile_file(path, robot, profile_config(overrides or []))

    def fit(self, request: FitRequest) -> FitOutcome:
        from torchcal.instruments.profile.commands import fit_profile

        return fit_profile(request.robot, request.data, request.out, request.overrides,
                           base_link=request.base_link, end_link=request.end_link, progress=request.progress,
                           previous=request.previous)

    def evaluate(self, request: EvaluateRequest) -> EvaluateOutcome:
        from torchcal.instruments.profile.commands import evaluate_profile

        return EvaluateOutcome(evaluate_profile(request.model, request.data, request.overrides, register=request.register))

    def options(self) -> type:
        from torchcal.instruments.profile.commands import ProfileFitConfig

        return ProfileFitConfig

    def evaluate_options(self) -> tuple[str, ...]:
        return ("joint_unit", "length_unit", "check_limits", "device", "model_dir")

    def twin(self) -> TwinSpec:
        from torchcal.instruments.profile.twin import ProfileTwinConfig, write_profile_case

        return TwinSpec(ProfileTwinConfig, write_profile_case, self.description)

    def contract_case(self) -> ContractCase:
        # depth noise 15 um: the fitted mounting leaves about that from the plane
        return ContractCase(
            twin_overrides=[],
            fit_file="profile.csv",
            test_file="profile.csv",
            metric="point_plane_rms_mm",
            bound=0.03,
        )
