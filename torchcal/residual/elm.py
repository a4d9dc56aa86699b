"""Extreme Learning Machine, as the compensation patent defines it.

One hidden layer ``H = sigmoid(X W^T + b)`` with input weights ``W`` uniform in ``[-1, 1]`` and
biases ``b`` uniform in ``[0, 1]``; output weights ``V = pinv(H) T``.

Solve: ``pinv`` (the patent's) or ridge ``V = (H^T H + lambda I)^-1 H^T T``. The default is ridge
with a small ``lambda``: sigmoid columns of a few hundred units are nearly collinear, and the
pseudo-inverse then fits noise with huge opposite weights (its cut-off is a numerical accident
of the SVD tolerance); a small ridge is the same estimate where ``H`` is well conditioned and a
stable one where it is not.
"""

from __future__ import annotations

from typing import Any

import torch

from torchcal.residual.base import ResidualHead


class ELMModule(torch.nn.Module):
    # buffers, registered in __init__ (declared so that type checkers see tensors, not Tensor | Module)
    weights: torch.Tensor
    bias: torch.Tensor
    output: torch.Tensor

    def __init__(self, weights: torch.Tensor, bias: torch.Tensor, output: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("weights", weights)
        self.register_buffer("bias", bias)
        self.register_buffer("output", output)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(features @ self.weights.T + self.bias) @ self.output


def solve_output_weights(hidden: torch.Tensor, targets: torch.Tensor, ridge: float | None) -> torch.Tensor:
    """``V`` for hidden activations ``(..., n, L)`` and targets ``(..., n, K)`` (batched over candidates)."""
    if ridge is None:
        return torch.linalg.pinv(hidden) @ targets
    return _ridge_solve(hidden.transpose(-1, -2) @ hidden, hidden.transpose(-1, -2) @ targets, ridge)


def candidate_activations_t(features: torch.Tensor, weights: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``H^T`` ``(C, L, n)`` of ``C`` candidate hidden layers (``weights (C, L, d)``, ``bias (C, L)``) on
    ``features (n, d)``.

    One matrix product for all candidates: broadcasting ``features @ weights^T`` over the candidates
    runs as ``C`` small products and took three times as long as this.
    """
    c, hidden, n_in = weights.shape
    linear = torch.addmm(bias.reshape(-1, 1), weights.reshape(-1, n_in), features.T)
    return linear.sigmoid_().reshape(c, hidden, -1)


def solve_candidates_output_weights(hidden_t: torch.Tensor, targets: torch.Tensor, ridge: float | None) -> torch.Tensor:
    """``V (C, L, K)`` of each candidate from its ``H^T (C, L, n)`` and the targets ``(n, K)`` all share.

    The estimate of :func:`solve_output_weights`, with ``H^T T`` as one product for all candidates.
    """
    if ridge is None:
        return solve_output_weights(hidden_t.transpose(-1, -2), targets, None)
    c, hidden, n = hidden_t.shape
    rhs = (hidden_t.reshape(-1, n) @ targets).reshape(c, hidden, -1)
    return _ridge_solve(hidden_t @ hidden_t.transpose(-1, -2), rhs, ridge)


def _ridge_solve(gram: torch.Tensor, rhs: torch.Tensor, ridge: float) -> torch.Tensor:
    """``(G + ridge * mean(diag G) I)^-1 R`` by Cholesky, batched."""
    eye = torch.eye(gram.shape[-1], dtype=gram.dtype, device=gram.device)
    scale = gram.diagonal(dim1=-2, dim2=-1).mean(-1)[..., None, None]
    chol = torch.linalg.cholesky(gram + ridge * scale * eye)
    return torch.cholesky_solve(rhs, chol)


class ELM(ResidualHead):
    """ELM with random ``W in [-1, 1]``, ``b in [0, 1]``.

    Args:
        hidden: hidden units ``L``.
        ridge: relative ridge ``lambda`` (times the mean diagonal of ``H^T H``); ``None`` = pinv.
        seed: seed of the random hidden layer.
    """

    name = "elm"
    tunes_on_validation = False

    @classmethod
    def from_options(cls, options: Any) -> ELM:
        return cls(hidden=options.residual_hidden, seed=options.seed)

    def __init__(self, hidden: int = 80, ridge: float | None = 1e-6, seed: int = 0) -> None:
        self.hidden, self.ridge, self.seed = hidden, ridge, seed
        self.weights: torch.Tensor | None = None
        self.bias: torch.Tensor | None = None
        self.output: torch.Tensor | None = None

    def set_hidden_layer(self, weights: torch.Tensor, bias: torch.Tensor) -> None:
        self.weights, self.bias = weights, bias

    def fit(self, x_train, y_train, x_val=None, y_val=None) -> ELM:
        if self.weights is None:
            gen = torch.Generator().manual_seed(self.seed)
            self.weights = torch.rand(self.hidden, x_train.shape[1], generator=gen, dtype=x_train.dtype) * 2 - 1
            self.bias = torch.rand(self.hidden, generator=gen, dtype=x_train.dtype)
        hidden = torch.sigmoid(x_train @ self.weights.T + self.bias)
        self.output = solve_output_weights(hidden, y_train, self.ridge)
        return self

    def module(self) -> torch.nn.Module:
        if self.weights is None or self.bias is None or self.output is None:
            raise RuntimeError("the ELM is not fitted: call fit first")
        return ELMModule(self.weights, self.bias, self.output)

    def settings(self) -> dict:
        return {"hidden": self.hidden, "ridge": self.ridge, "seed": self.seed}

    @classmethod
    def from_state(cls, settings: dict, state: dict[str, torch.Tensor]) -> ELM:
        head = cls(hidden=settings["hidden"], ridge=settings["ridge"], seed=settings["seed"])
        head.weights, head.bias, head.output = state["weights"], state["bias"], state["output"]
        return head
