"""Metaheuristics: the contract every registered optimizer satisfies, and Mayfly vs random search."""

from __future__ import annotations

import statistics

import pytest
import torch

from torchcal.optimize import OPTIMIZERS, Mayfly, RandomSearch


def sphere(x):
    return (x**2).sum(-1)


def rastrigin(x):
    return 10 * x.shape[-1] + (x**2 - 10 * torch.cos(2 * torch.pi * x)).sum(-1)


def rosenbrock(x):
    return (100 * (x[:, 1:] - x[:, :-1] ** 2) ** 2 + (1 - x[:, :-1]) ** 2).sum(-1)


def _small(name):
    return Mayfly(population=8, iterations=15) if name == "mayfly" else RandomSearch(evaluations=400)


@pytest.mark.parametrize("name", sorted(OPTIMIZERS))
def test_contract_bounds_reproducible_and_improving(name):
    lower = torch.tensor([-2.0, 0.5, -1.0], dtype=torch.float64)
    upper = torch.tensor([1.0, 3.0, 4.0], dtype=torch.float64)
    seen = []

    def fitness(x):
        assert bool(((x >= lower) & (x <= upper)).all())
        seen.append(x.shape[0])
        return ((x - torch.tensor([0.3, 1.0, 2.0], dtype=torch.float64)) ** 2).sum(-1)

    a = _small(name).minimize(fitness, lower, upper, seed=3)
    b = _small(name).minimize(fitness, lower, upper, seed=3)
    assert torch.equal(a.best_x, b.best_x) and a.best_f == b.best_f
    assert a.n_evaluations == sum(seen) // 2  # both runs counted in `seen`
    assert a.history[-1] <= a.history[0]
    assert a.best_f < 0.5


@pytest.mark.parametrize("function, bound", [(sphere, 5.12), (rastrigin, 5.12), (rosenbrock, 5.0)], ids=["sphere", "rastrigin", "rosenbrock"])
def test_mayfly_beats_random_search_at_equal_evaluations_in_10d(function, bound):
    lower = -bound * torch.ones(10, dtype=torch.float64)
    upper = -lower
    mayfly = Mayfly(population=10, iterations=40)
    budget = mayfly.evaluations_per_run()
    ours = statistics.median(mayfly.minimize(function, lower, upper, seed=s).best_f for s in range(3))
    theirs = statistics.median(RandomSearch(evaluations=budget).minimize(function, lower, upper, seed=s).best_f for s in range(3))
    assert ours < 0.5 * theirs


def test_initialization_variants_stay_in_the_box():
    lower, upper = torch.zeros(5, dtype=torch.float64), torch.ones(5, dtype=torch.float64) * 2
    for tent in (True, False):
        for obl in (True, False):
            opt = Mayfly(population=6, iterations=2, tent_init=tent, opposition_init=obl)
            x, f, used = opt._initial(sphere, lower, upper, torch.Generator().manual_seed(0))
            assert x.shape == (12, 5) and used == (24 if obl else 12)
            assert bool(((x >= 0) & (x <= 2)).all())
            assert bool((f[:-1] <= f[1:]).all())  # best first
