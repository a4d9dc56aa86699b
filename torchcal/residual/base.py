"""The residual-head interface.

A head maps features of the joint angles to the TCP position error the geometric model leaves,
in the ``base`` frame, in mm (training targets are scaled to mm for conditioning; callers
convert). Every head can export itself as a plain ``torch.nn.Module`` (for ONNX) and store its
state as tensors (for safetensors) plus JSON-able settings.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import torch


class ResidualHead(ABC):
    """A learned model of the geometric residual."""

    name = "head"
    #: whether ``fit`` steers itself with its validation pair (search, early stopping)
    tunes_on_validation = True
    #: modules ``fit`` imports on first use: a worker process imports them before its first fit
    #: (:func:`torchcal.core.workers.warm_up`)
    imports: tuple[str, ...] = ()

    @abstractmethod
    def fit(self, x_train: torch.Tensor, y_train: torch.Tensor, x_val: torch.Tensor, y_val: torch.Tensor) -> ResidualHead:
        """Fit on features ``(n, F)`` and targets ``(n, K)``; the validation pair may steer early stopping."""

    @abstractmethod
    def module(self) -> torch.nn.Module:
        """A plain module computing the prediction from features."""

    @abstractmethod
    def settings(self) -> dict:
        """JSON-able hyperparameters needed to rebuild the module."""

    @classmethod
    def from_options(cls, options: Any) -> ResidualHead:
        """The candidate a fit's options configure (``options``: a ``FitConfig``; ``seed``, and the
        ``residual_*`` fields a head reads). The residual stage builds every head through this hook."""
        return cls()

    def refit_output(self, x: torch.Tensor, y: torch.Tensor) -> ResidualHead | None:
        """Refit only what needs no model selection on ``(x, y)``, keeping what the head's own search
        chose; ``None`` (the default): the head has no such part and is refitted whole."""
        return None

    @classmethod
    def from_state(cls, settings: dict, state: dict[str, torch.Tensor]) -> ResidualHead:
        """The fitted head that :meth:`settings` and :meth:`state` describe (a model folder's head)."""
        raise NotImplementedError(f"{cls.__name__} cannot be rebuilt from a stored state")

    def predict(self, features: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            return self.module().to(features.dtype)(features)

    def state(self) -> dict[str, torch.Tensor]:
        return {k: v.detach().cpu().contiguous() for k, v in self.module().state_dict().items()}


def rms(a: torch.Tensor) -> float:
    """Root mean square of the per-sample vector norm."""
    return float(a.norm(dim=-1).pow(2).mean().sqrt())
