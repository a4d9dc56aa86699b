"""Geometric identification: solvers, identifiability, uncertainty and pose selection."""

from torchcal.identify.base import Identifier, SolveResult
from torchcal.identify.gauss_newton import GaussNewton
from torchcal.identify.lasso import LassoIdentifier
from torchcal.identify.lm import LevenbergMarquardt

IDENTIFIERS: dict[str, type[Identifier]] = {
    "lm": LevenbergMarquardt,
    "gn": GaussNewton,
    "lasso": LassoIdentifier,
}

__all__ = ["IDENTIFIERS", "GaussNewton", "Identifier", "LassoIdentifier", "LevenbergMarquardt", "SolveResult"]
