"""MLP residual head trained with Lightning Fabric: Adam on shuffled mini-batches, early stopping on the
validation loss, the best epoch kept.

The network is small (three layers of 64 on a batch of 128) and a step costs well under a
millisecond, so a ``Trainer``'s per-step hooks (callbacks, logging, closures, checkpoint files) cost
more than the step: with it the same training took about three times as long (docs/benchmarks.md).
Fabric keeps Lightning's device, precision and backward handling and leaves the loop to this module,
which computes exactly what that trainer computed (same initialization, batches, optimizer and
scheduler steps, stopping rule and kept epoch; ``tests/residual/test_heads.py`` checks this against
the ``Trainer``).
"""

from __future__ import annotations

import math
from typing import Any

import torch

from torchcal.optimize.base import progress_bar
from torchcal.residual.base import ResidualHead


class Scale(torch.nn.Module):
    """Multiply by a fixed factor: the network learns unit-scale targets, the head outputs mm."""

    # buffers, registered in __init__ (declared so that type checkers see tensors, not Tensor | Module)
    factor: torch.Tensor

    def __init__(self, factor: float) -> None:
        super().__init__()
        self.register_buffer("factor", torch.tensor(float(factor), dtype=torch.float64))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.factor


def _epoch_mean(loss: torch.Tensor, n: int) -> torch.Tensor:
    """The epoch's validation loss as a trainer's metric logger reduces one batch of ``n``: ``(0 + loss n) / n``
    (not always ``loss`` to the last bit; kept so that the stopping rule sees the same numbers)."""
    return (torch.tensor(0.0) + loss * n) / torch.tensor(n)


def make_network(n_in: int, n_out: int, width: int, depth: int, output_scale: float = 1.0) -> torch.nn.Sequential:
    layers: list[torch.nn.Module] = []
    size = n_in
    for _ in range(depth):
        layers += [torch.nn.Linear(size, width), torch.nn.Tanh()]
        size = width
    layers += [torch.nn.Linear(size, n_out), Scale(output_scale)]
    return torch.nn.Sequential(*layers)


class MLPHead(ResidualHead):
    """Tanh MLP (smooth, like the errors it models) trained by Adam with MSE loss.

    Args:
        width, depth: hidden layer size and count (three tanh layers of 64: on the twin the third
            layer lowered the held-out RMS from 0.097 to 0.082 mm, same data, same seed).
        max_epochs, patience: training budget and early-stopping patience (epochs).
        learning_rate, batch_size, weight_decay: optimizer settings.
        seed: initialization and shuffling seed.
        progress: Lightning's progress bar.
    """

    name = "mlp"
    # Lightning Fabric, and torch._dynamo (which Adam's constructor imports): about 2 s on first use
    imports = ("lightning.fabric", "torch._dynamo")

    @classmethod
    def from_options(cls, options: Any) -> MLPHead:
        return cls(seed=options.seed, progress=False)

    def __init__(self, width: int = 64, depth: int = 3, max_epochs: int = 600, patience: int = 60,
                 learning_rate: float = 3e-3, batch_size: int = 128, weight_decay: float = 0.0, seed: int = 0,
                 progress: bool = False) -> None:
        self.width, self.depth, self.max_epochs, self.patience = width, depth, max_epochs, patience
        self.learning_rate, self.batch_size, self.weight_decay = learning_rate, batch_size, weight_decay
        self.seed, self.progress = seed, progress
        self.network: torch.nn.Sequential | None = None
        self.output_scale = 1.0  # the targets' spread, set by fit (the network learns unit-scale targets)
        self.epochs_trained = 0

    def fit(self, x_train, y_train, x_val, y_val) -> MLPHead:
        """Train on ``(x_train, y_train)``; ``(x_val, y_val)`` steers the step size, early stopping and the
        kept epoch (the one of lowest validation loss)."""
        self.output_scale = float(y_train.std().clamp_min(1e-12))
        with torch.random.fork_rng(devices=[]):  # the seeded initialization leaves the global generator alone
            torch.manual_seed(self.seed)
            network = make_network(x_train.shape[1], y_train.shape[1], self.width, self.depth, self.output_scale).to(x_train.dtype)
        optimizer = torch.optim.Adam(network.parameters(), lr=self.learning_rate, weight_decay=self.weight_decay)
        # imported here, not at the top: commands that do not train an MLP skip Lightning's import time
        from lightning.fabric import Fabric

        fabric = Fabric(accelerator="cpu", devices=1)
        trained, fabric_optimizer = fabric.setup(network, optimizer)
        # halve the step when validation stalls: Adam's noise floor, not the model, limits the fit
        plateau = torch.optim.lr_scheduler.ReduceLROnPlateau(optimizer, factor=0.5, patience=max(2, self.patience // 4))
        # the batches of a shuffling loader: one seeded permutation per epoch, cut into batches in order
        order = torch.Generator().manual_seed(self.seed)
        batches = torch.utils.data.BatchSampler(torch.utils.data.RandomSampler(range(len(x_train)), generator=order),
                                                self.batch_size, drop_last=False)
        best_loss, best_state, stalled, epoch = math.inf, None, 0, 0
        with progress_bar(self.progress, self.max_epochs, "MLP training") as bar:
            while epoch < self.max_epochs:
                network.train()
                for idx in batches:
                    fabric_optimizer.zero_grad()
                    fabric.backward(torch.nn.functional.mse_loss(trained(x_train[idx]), y_train[idx]))
                    fabric_optimizer.step()
                network.eval()
                with torch.no_grad():
                    loss = float(_epoch_mean(torch.nn.functional.mse_loss(network(x_val), y_val), len(x_val)))
                epoch += 1
                bar.advance()
                if best_state is None or loss < best_loss:  # the kept epoch: strictly lower validation loss
                    best_state = {k: v.detach().clone() for k, v in network.state_dict().items()}
                if not math.isfinite(loss):
                    break
                if loss < best_loss:  # early stopping: ``patience`` epochs without a strictly lower loss
                    best_loss, stalled = loss, 0
                else:
                    stalled += 1
                    if stalled >= self.patience:
                        break
                plateau.step(loss)
        self.epochs_trained = epoch
        assert best_state is not None
        network.load_state_dict(best_state)
        self.network = network.eval()
        return self

    def module(self) -> torch.nn.Module:
        return self._fitted()

    def _fitted(self) -> torch.nn.Sequential:
        if self.network is None:
            raise RuntimeError("the MLP head is not fitted: call fit first")
        return self.network

    def settings(self) -> dict:
        network = self._fitted()
        return {"width": self.width, "depth": self.depth, "n_in": network[0].in_features,
                "n_out": network[-2].out_features, "seed": self.seed, "output_scale": self.output_scale}

    @classmethod
    def from_state(cls, settings: dict, state: dict[str, torch.Tensor]) -> MLPHead:
        head = cls(width=settings["width"], depth=settings["depth"], seed=settings["seed"])
        net = make_network(settings["n_in"], settings["n_out"], settings["width"], settings["depth"],
                           settings["output_scale"]).to(torch.float64)
        net.load_state_dict(state)
        head.network = net.eval()
        head.output_scale = float(settings["output_scale"])
        return head
