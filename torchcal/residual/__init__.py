"""Learned residual heads: what the geometric model leaves, as a function of the joints."""

from torchcal.residual.base import ResidualHead, rms
from torchcal.residual.elm import ELM
from torchcal.residual.mlp import MLPHead
from torchcal.residual.mma_elm import MayflyELM

HEADS: dict[str, type[ResidualHead]] = {"elm": ELM, "mma-elm": MayflyELM, "mlp": MLPHead}

__all__ = ["ELM", "HEADS", "MLPHead", "MayflyELM", "ResidualHead", "rms"]
