"""ELM whose hidden layer (W, b) is chosen by the improved Mayfly optimizer (MMA-ELM).

A candidate is the flattened ``[W, b]`` inside the patent's box (``W in [-1, 1]``,
``b in [0, 1]``); its fitness is the validation RMS of the ELM built from it (output weights
solved on the training part). All candidates of a generation are evaluated in one batched
solve.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from torchcal.optimize.base import Metaheuristic, OptimizeResult
from torchcal.optimize.mayfly import Mayfly
from torchcal.residual.base import ResidualHead
from torchcal.residual.elm import ELM, candidate_activations_t, solve_candidates_output_weights


class MayflyELM(ResidualHead):
    """MMA-ELM.

    Args:
        hidden: hidden units.
        population, iterations: Mayfly settings (males and females each; generations).
        ridge: as :class:`~torchcal.residual.elm.ELM`.
        seed: optimizer seed.
        progress: show a progress bar.
        optimizer: the metaheuristic that searches the hidden layer (default: Mayfly with
            ``population`` and ``iterations``); its ``on_iteration`` hook receives this head's.
    """

    name = "mma-elm"

    @classmethod
    def from_options(cls, options: Any) -> MayflyELM:
        return cls(hidden=options.residual_hidden, population=options.mayfly_population,
                   iterations=options.mayfly_iterations, seed=options.seed, progress=False)

    def __init__(self, hidden: int = 80, population: int = 20, iterations: int = 50, ridge: float | None = 1e-6,
                 seed: int = 0, progress: bool = False, optimizer: Metaheuristic | None = None) -> None:
        # the search over hidden layers: any metaheuristic (``optimize.OPTIMIZERS``); Mayfly by default
        self.optimizer = optimizer if optimizer is not None else Mayfly(population=population, iterations=iterations)
        self.hidden, self.population, self.iterations = hidden, population, iterations
        self.ridge, self.seed, self.progress = ridge, seed, progress
        # Optional observer of the search, (iteration, best validation RMS mm); a study prunes with it.
        self.on_iteration: Callable[[int, float], None] | None = None
        self.elm = ELM(hidden=hidden, ridge=ridge, seed=seed)
        self.search: OptimizeResult | None = None

    def fit(self, x_train, y_train, x_val, y_val) -> MayflyELM:
        n_in = x_train.shape[1]
        dim = self.hidden * (n_in + 1)
        lower = torch.cat([-torch.ones(self.hidden * n_in), torch.zeros(self.hidden)]).to(x_train.dtype)
        upper = torch.ones(dim, dtype=x_train.dtype)

        def unpack(c: torch.Tensor):
            return c[:, : self.hidden * n_in].reshape(-1, self.hidden, n_in), c[:, self.hidden * n_in :]

        def fitness(candidates: torch.Tensor) -> torch.Tensor:
            w, b = unpack(candidates)
            out = solve_candidates_output_weights(candidate_activations_t(x_train, w, b), y_train, self.ridge)
            err = candidate_activations_t(x_val, w, b).transpose(-1, -2) @ out - y_val
            return err.norm(dim=-1).pow(2).mean(-1).sqrt()

        search = self.optimizer.minimize(fitness, lower, upper, seed=self.seed, progress=self.progress,
                                    on_iteration=self.on_iteration)
        self.search = search
        w, b = unpack(search.best_x.unsqueeze(0))
        self.elm.set_hidden_layer(w[0], b[0])
        self.elm.fit(x_train, y_train)
        return self

    def refit_output(self, x: torch.Tensor, y: torch.Tensor) -> MayflyELM:
        """Re-solve the output weights on ``(x, y)``, keeping the hidden layer the search chose."""
        if self.search is None:
            raise RuntimeError("refit_output needs a fitted MMA-ELM: call fit first (the search chooses the hidden layer)")
        self.elm.fit(x, y)
        return self

    def module(self) -> torch.nn.Module:
        return self.elm.module()

    def settings(self) -> dict:
        return {"hidden": self.hidden, "population": self.population, "iterations": self.iterations,
                "ridge": self.ridge, "seed": self.seed}

    @classmethod
    def from_state(cls, settings: dict, state: dict[str, torch.Tensor]) -> MayflyELM:
        head = cls(**settings)
        head.elm = ELM.from_state({"hidden": settings["hidden"], "ridge": settings["ridge"], "seed": settings["seed"]}, state)
        return head
