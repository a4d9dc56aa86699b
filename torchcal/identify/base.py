"""The identifier interface: every solver takes a problem and a start and returns a solution."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import torch

from torchcal.identify.problem import CalibrationProblem


@dataclass
class SolveResult:
    """Solution of a calibration problem.

    Attributes:
        x: full parameter vector at the solution (SI).
        free: indices of the parameters that were estimated.
        cost: final ``0.5 * |r|^2`` (m^2).
        iterations: solver iterations.
        converged: whether a convergence test (not the iteration cap) stopped it.
        history: cost per iteration.
        selected: for sparse solvers, the parameters kept (names); otherwise all free ones.
    """

    x: torch.Tensor
    free: torch.Tensor
    cost: float
    iterations: int
    converged: bool
    history: list[float] = field(default_factory=list)
    selected: list[str] = field(default_factory=list)
    message: str = ""


class Identifier(ABC):
    """A method that estimates ``problem.free`` starting from ``x0``."""

    name: str = "identifier"

    @abstractmethod
    def solve(self, problem: CalibrationProblem, x0: torch.Tensor) -> SolveResult:
        """Estimate the free parameters; ``x0`` fixes every other parameter."""
