"""Which twin ``torchcal simulate instrument=<name>`` writes.

Each instrument registers a configuration dataclass (its ``key=value`` overrides) and a writer
``write(out_dir, config) -> {name: path}``. The default, ``tracker``, is the geometric twin of
:mod:`torchcal.sim.twin`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from torchcal.errors import TorchcalError


@dataclass(frozen=True)
class TwinWriter:
    """A twin kind: its config class and the function that writes a case."""

    config_factory: Callable[[], Any]
    write: Callable[[Path, Any], dict[str, Path]]
    description: str


def _tracker() -> TwinWriter:
    from torchcal.sim.twin import TwinConfig, write_twin_case

    return TwinWriter(TwinConfig, write_twin_case, "laser-tracker points (train.csv, test.csv)")


def _stiffness() -> TwinWriter:
    from torchcal.sim.stiffness_case import StiffnessCaseConfig, write_stiffness_twin_case

    return TwinWriter(
        StiffnessCaseConfig,
        write_stiffness_twin_case,
        "loading rig (robot.yaml, stiffness_train.csv, stiffness_test.csv, stiffness_truth.json)",
    )


def _tracer() -> TwinWriter:
    from torchcal.sim.tracer_case import TracerTwinConfig, write_tracer_case

    return TwinWriter(TracerTwinConfig, write_tracer_case, "multi-station laser-tracer lengths (lengths.csv, test.csv)")


def _profile() -> TwinWriter:
    from torchcal.sim.profile_twin import ProfileTwinConfig, write_profile_case

    return TwinWriter(ProfileTwinConfig, write_profile_case, "line-laser profile sensor on a plane target (profile.csv)")


def _sockets() -> TwinWriter:
    from torchcal.instruments.sockets.twin import SocketsTwinConfig, write_sockets_case

    return TwinWriter(SocketsTwinConfig, write_sockets_case, "ball in two-socket fixtures (sockets.csv, sockets_test.csv)")


# Loaders are lazy so that ``simulate`` imports only the instrument it writes.
TWIN_WRITERS: dict[str, Callable[[], TwinWriter]] = {
    "tracker": _tracker,
    "stiffness": _stiffness,
    "tracer": _tracer,
    "profile": _profile,
    "sockets": _sockets,
}


def twin_writer(instrument: str) -> TwinWriter:
    """The writer registered for ``instrument``; a clear error for an unknown name."""
    if instrument not in TWIN_WRITERS:
        raise TorchcalError(f"unknown instrument '{instrument}'; choose one of {sorted(TWIN_WRITERS)}")
    return TWIN_WRITERS[instrument]()


def split_instrument(overrides: list[str], default: str = "tracker") -> tuple[str, list[str]]:
    """Take ``instrument=<name>`` out of a list of ``key=value`` overrides."""
    instrument = default
    rest = []
    for item in overrides:
        key, _, value = item.partition("=")
        if key.strip() == "instrument":
            instrument = value.strip()
        else:
            rest.append(item)
    return instrument, rest
