"""Uniform random search: the baseline every metaheuristic must beat at equal evaluations."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchcal.optimize.base import Fitness, Metaheuristic, OptimizeResult


class RandomSearch(Metaheuristic):
    """Evaluate ``evaluations`` uniform samples in batches of ``batch``."""

    name = "random"

    def __init__(self, evaluations: int = 2000, batch: int = 40) -> None:
        self.evaluations = evaluations
        self.batch = batch

    def minimize(self, fitness: Fitness, lower, upper, *, seed: int = 0, progress: bool = False,
                 on_iteration: Callable[[int, float], None] | None = None) -> OptimizeResult:
        gen = torch.Generator().manual_seed(seed)
        if self.evaluations < 1:
            raise ValueError(f"evaluations must be >= 1, got {self.evaluations}")
        best_x: torch.Tensor | None = None
        best_f, history, used = float("inf"), [], 0
        while used < self.evaluations:
            n = min(self.batch, self.evaluations - used)
            x = lower + torch.rand(n, lower.shape[0], generator=gen, dtype=lower.dtype) * (upper - lower)
            f = fitness(x)
            used += n
            k = int(torch.argmin(f))
            # the first batch's best is kept even if not finite (as Mayfly's initial population):
            # a result always has a candidate
            if best_x is None or float(f[k]) < best_f:
                best_f, best_x = float(f[k]), x[k].clone()
            history.append(best_f)
            if on_iteration is not None:
                on_iteration(len(history), best_f)
        assert best_x is not None  # evaluations >= 1: the loop ran
        return OptimizeResult(best_x=best_x, best_f=best_f, history=history, n_evaluations=used)
