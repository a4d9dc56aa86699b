"""``fit`` and ``evaluate`` for measurement kinds other than tracker points.

The tracker pipeline lives in :mod:`torchcal.pipeline`. Every other kind registers here a
``fit(robot_path, data_path, out_dir, overrides, *, base_link, end_link) -> Path`` and an
``evaluate(model_dir, data_path, overrides, *, register) -> dict`` handler, loaded lazily so
that a command imports only what its file needs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from torchcal.errors import TorchcalError


@dataclass(frozen=True)
class KindHandlers:
    """What ``fit`` and ``evaluate`` do with one measurement kind (``None``: not supported)."""

    fit: Callable[..., Path] | None = None
    evaluate: Callable[..., dict] | None = None


def _profile() -> KindHandlers:
    from torchcal.measure.profile_commands import evaluate_profile, fit_profile

    return KindHandlers(fit=fit_profile, evaluate=evaluate_profile)


# kind -> loader of its handlers; the tracker kind is handled by torchcal.pipeline directly.
def _stiffness() -> KindHandlers:
    from torchcal.stiffness_stage import handlers

    return handlers()


def _tracer() -> KindHandlers:
    from torchcal.tracer_commands import handlers

    return handlers()


def _sockets() -> KindHandlers:
    from torchcal.instruments.sockets.commands import handlers

    return handlers()


def _length_station() -> KindHandlers:
    from torchcal.instruments.length_station.commands import handlers

    return handlers()


KIND_HANDLERS: dict[str, Callable[[], KindHandlers]] = {
    "length_station": _length_station,
    "sockets": _sockets,
    "profile": _profile,
    "stiffness": _stiffness,
    "tracer": _tracer,
}


def handlers_for(kind: str, command: str) -> KindHandlers:
    """Handlers of ``kind``; a clear error where ``command`` does not support that kind."""
    loader = KIND_HANDLERS.get(kind)
    handlers = loader() if loader else None
    if handlers is None or getattr(handlers, command) is None:
        raise TorchcalError(f"'{command}' does not support {kind} files yet")
    return handlers
