"""The instrument interface: what every measuring instrument model implements.

An instrument turns true reflector/TCP points into the columns of its measurement file
(:meth:`Instrument.simulate`) and, given predicted points and its own nuisance parameters (the
unknown frame of a tracker, the stations and dead paths of a tracer...), returns whitened
residuals (:meth:`Instrument.residuals`) that an identifier stacks with the robot's. Points are
``(n, 3)`` in m, in the frame the caller predicts them in (the robot ``base`` frame for an
identifier); columns are SI tensors keyed by their file column names (the data layer converts the
file's mm/deg to SI).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import ClassVar

import torch


def joint_columns(n_joints: int) -> list[str]:
    """``["q1", ..., "qN"]``: the joint columns every measurement file starts with."""
    return [f"q{k + 1}" for k in range(n_joints)]


class Instrument(ABC):
    """A measuring instrument: file columns, a noise model to simulate, residuals to identify with.

    Attributes:
        name: registry name (``"tracker"``, ``"tracer"``, ...).
    """

    name: ClassVar[str]

    @abstractmethod
    def columns(self, n_joints: int) -> list[str]:
        """Column names this instrument reads from a CSV, joint columns first."""

    @abstractmethod
    def simulate(self, true_points_m: torch.Tensor, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """Noisy measurement columns (SI, ``(n,)`` each, NaN where not measured) of ``(n, 3)`` true points.

        The joint columns are the caller's; only this instrument's own columns are returned.
        """

    @abstractmethod
    def initial_params(self, points_m: torch.Tensor, measured: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Starting nuisance parameters ``(k,)`` given approximate points ``(n, 3)`` (e.g. nominal FK)."""

    @abstractmethod
    def residuals(
        self, points_m: torch.Tensor, measured: Mapping[str, torch.Tensor], params: torch.Tensor
    ) -> torch.Tensor:
        """Whitened residuals (model minus measurement over sigma), 1-D, differentiable in both inputs.

        Missing measurements contribute no residual; the length of the output depends only on
        which entries of ``measured`` are finite.
        """
