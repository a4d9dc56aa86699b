"""The metaheuristic interface: minimize a batched fitness over a box."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

Fitness = Callable[[torch.Tensor], torch.Tensor]
"""Maps candidates ``(pop, dim)`` to fitness values ``(pop,)``; lower is better."""


@dataclass
class OptimizeResult:
    """Best candidate, its fitness, best-so-far per iteration and the evaluation count."""

    best_x: torch.Tensor
    best_f: float
    history: list[float] = field(default_factory=list)
    n_evaluations: int = 0


class Metaheuristic(ABC):
    """A population method; ``evaluations`` bounds its fitness calls (candidates evaluated)."""

    name = "metaheuristic"

    @abstractmethod
    def minimize(
        self,
        fitness: Fitness,
        lower: torch.Tensor,
        upper: torch.Tensor,
        *,
        seed: int = 0,
        progress: bool = False,
        on_iteration: Callable[[int, float], None] | None = None,
    ) -> OptimizeResult:
        """Minimize ``fitness`` over the box ``[lower, upper]`` (``(dim,)`` each).

        ``on_iteration(k, best_f)`` is called after iteration ``k`` (1-based: a generation, a
        batch) with the best fitness so far; it may raise to stop the search (a study pruning a
        poor trial does).
        """


def progress_bar(enabled: bool, total: int, description: str):
    """A rich progress bar, or a no-op stand-in."""
    if not enabled:
        class _Null:
            def __enter__(self):
                return self

            def __exit__(self, *exc):
                return False

            def advance(self, *_args, **_kw):
                return None

        return _Null()
    from rich.progress import Progress

    class _Bar:
        def __enter__(self):
            self.progress = Progress(transient=True)
            self.progress.__enter__()
            self.task = self.progress.add_task(description, total=total)
            return self

        def __exit__(self, *exc):
            return self.progress.__exit__(*exc)

        def advance(self, amount: int = 1):
            self.progress.advance(self.task, amount)

    return _Bar()
