"""Learned residual heads: what the geometric model leaves, as a function of the joints."""

from torchcal.core.errors import TorchcalError
from torchcal.residual.base import ResidualHead, rms
from torchcal.residual.elm import ELM
from torchcal.residual.mlp import MLPHead
from torchcal.residual.mma_elm import MayflyELM

HEADS: dict[str, type[ResidualHead]] = {"elm": ELM, "mma-elm": MayflyELM, "mlp": MLPHead}

#: Heads that ``residual=auto`` cross-validates.
AUTO_HEADS = ("mma-elm", "mlp")


def head_names(residual: str) -> tuple[str, ...]:
    """Head names of a ``residual`` option (``auto``, ``none``, a name or names joined by ``+``)."""
    if residual == "none":
        return ()
    names = AUTO_HEADS if residual == "auto" else tuple(n.strip() for n in residual.split("+"))
    for name in names:
        if name not in HEADS:
            raise TorchcalError(f"unknown residual head '{name}'; choose auto, none or any of {sorted(HEADS)} (joined by +)")
    return names

__all__ = ["AUTO_HEADS", "ELM", "HEADS", "MLPHead", "MayflyELM", "ResidualHead", "head_names", "rms"]
