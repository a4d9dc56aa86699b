"""RandomSearch always returns a candidate, as Mayfly does."""

import math

import pytest
import torch

from torchcal.optimize import RandomSearch


def test_a_fitness_without_finite_values_still_gives_a_candidate():
    lower, upper = -torch.ones(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64)
    result = RandomSearch(evaluations=20, batch=8).minimize(
        lambda x: torch.full((len(x),), math.inf, dtype=x.dtype), lower, upper)
    assert isinstance(result.best_x, torch.Tensor) and result.best_x.shape == (3,)
    assert bool(((result.best_x >= lower) & (result.best_x <= upper)).all())
    assert result.n_evaluations == 20


def test_no_evaluations_is_an_error():
    with pytest.raises(ValueError, match="evaluations"):
        RandomSearch(evaluations=0).minimize(lambda x: x.sum(-1), torch.zeros(2), torch.ones(2))
