"""Metaheuristic optimizers over a box (a general interface; the ELM tuner is one client)."""

from torchcal.optimize.base import Metaheuristic, OptimizeResult
from torchcal.optimize.mayfly import Mayfly
from torchcal.optimize.random_search import RandomSearch

OPTIMIZERS: dict[str, type[Metaheuristic]] = {"mayfly": Mayfly, "random": RandomSearch}

__all__ = ["OPTIMIZERS", "Mayfly", "Metaheuristic", "OptimizeResult", "RandomSearch"]
