"""The contract every metaheuristic meets: a box-constrained minimum found, the box kept, the hook called.

Run it for the registered optimizers (``tests/optimize/test_metaheuristic_contract.py`` does) or for one that
lives outside torchcal::

    from torchcal.testing.metaheuristic_contract import MetaheuristicContract

    class TestMySearch(MetaheuristicContract):
        def make(self):
            return MySearch(budget=2000)

The truth is closed form: a shifted sphere whose minimum (0 at ``CENTRE``) lies inside the box.
Needs pytest.
"""

from __future__ import annotations

import itertools

import pytest
import torch

from torchcal.optimize.base import Metaheuristic, OptimizeResult

#: the sphere's minimum, inside the box [-1, 1]^4
CENTRE = torch.tensor([0.3, -0.2, 0.5, 0.1], dtype=torch.float64)
LOWER, UPPER = -torch.ones(4, dtype=torch.float64), torch.ones(4, dtype=torch.float64)


def sphere(candidates: torch.Tensor) -> torch.Tensor:
    """``|x - CENTRE|^2`` of each candidate ``(pop, 4)``; minimum 0."""
    return (candidates - CENTRE).pow(2).sum(-1)


class MetaheuristicContract:
    """Tests every metaheuristic passes; subclasses implement :meth:`make` (and may loosen :attr:`bound`)."""

    #: fitness the search must reach on the 4-D sphere (random search over the box reaches it in ~2000)
    bound: float = 0.05

    def make(self) -> Metaheuristic:
        raise NotImplementedError

    def test_finds_the_minimum_inside_the_box(self) -> None:
        seen: list[torch.Tensor] = []

        def fitness(x: torch.Tensor) -> torch.Tensor:
            seen.append(x.detach().clone())
            return sphere(x)

        result = self.make().minimize(fitness, LOWER, UPPER, seed=0)
        assert isinstance(result, OptimizeResult)
        assert result.best_f < self.bound
        assert float(sphere(result.best_x.unsqueeze(0))) == pytest.approx(result.best_f, rel=1e-12, abs=1e-15)
        every = torch.cat(seen)
        assert bool(((every >= LOWER) & (every <= UPPER)).all()), "a candidate left the box"
        assert result.n_evaluations == len(every)

    def test_best_so_far_never_worsens_and_the_hook_sees_it(self) -> None:
        calls: list[tuple[int, float]] = []
        result = self.make().minimize(sphere, LOWER, UPPER, seed=1, on_iteration=lambda k, f: calls.append((k, f)))
        assert all(b <= a for a, b in zip(result.history, result.history[1:]))
        assert calls, "on_iteration was never called"
        assert [k for k, _ in calls] == list(range(calls[0][0], calls[0][0] + len(calls)))
        assert all(b <= a for (_, a), (_, b) in itertools.pairwise(calls))
        assert calls[-1][1] == pytest.approx(result.best_f)

    def test_a_raising_hook_stops_the_search(self) -> None:
        class Stop(Exception):
            pass

        def stop(k: int, f: float) -> None:
            raise Stop

        with pytest.raises(Stop):
            self.make().minimize(sphere, LOWER, UPPER, seed=0, on_iteration=stop)

    def test_same_seed_same_result(self) -> None:
        a = self.make().minimize(sphere, LOWER, UPPER, seed=3)
        b = self.make().minimize(sphere, LOWER, UPPER, seed=3)
        assert torch.equal(a.best_x, b.best_x) and a.best_f == b.best_f
