"""MLP residual head trained with Lightning (early stopping on validation loss, best checkpoint).

Lightning is imported inside :meth:`MLPHead.fit` only: commands that do not train stay light.
The best checkpoint is reloaded with ``torch.load(..., weights_only=True)``.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import torch

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
        import logging
        import warnings

        import lightning as L
        from lightning.pytorch.callbacks import EarlyStopping, ModelCheckpoint

        # Lightning's informational banners (devices, tips) say nothing about this fit
        for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
            logging.getLogger(name).setLevel(logging.WARNING)
        warnings.filterwarnings("ignore", message=".*treespec.*")
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")

        L.seed_everything(self.seed, verbose=False)
        self.output_scale = float(y_train.std().clamp_min(1e-12))
        network = make_network(x_train.shape[1], y_train.shape[1], self.width, self.depth, self.output_scale).to(x_train.dtype)
        head = self

        class Module(L.LightningModule):
            def __init__(self) -> None:
                super().__init__()
                self.net = network

            def forward(self, x):
                return self.net(x)

            def training_step(self, batch, _):
                x, y = batch
                # not logged: nothing reads it, and a log call per step costs more than the step
                return torch.nn.functional.mse_loss(self.net(x), y)

            def validation_step(self, batch, _):
                x, y = batch
                self.log("val_loss", torch.nn.functional.mse_loss(self.net(x), y), prog_bar=True)

            def configure_optimizers(self):
                optimizer = torch.optim.Adam(self.parameters(), lr=head.learning_rate, weight_decay=head.weight_decay)
                # halve the step when validation stalls: Adam's noise floor, not the model, limits the fit
                plateau = torch.optim.lr_scheduler.ReduceLROnPlateau(optimizer, factor=0.5, patience=max(2, head.patience // 4))
                return {"optimizer": optimizer, "lr_scheduler": {"scheduler": plateau, "monitor": "val_loss"}}

        class Data(L.LightningDataModule):
            def train_dataloader(self):
                ds = torch.utils.data.TensorDataset(x_train, y_train)
                gen = torch.Generator().manual_seed(head.seed)
                # the batches of shuffle=True, fetched as one index list per batch (``batch_size=None``):
                # the same batches without a per-sample fetch and collate, which cost more than the step
                batches = torch.utils.data.BatchSampler(torch.utils.data.RandomSampler(ds, generator=gen), head.batch_size, drop_last=False)
                return torch.utils.data.DataLoader(ds, batch_size=None, sampler=batches)

            def val_dataloader(self):
                ds = torch.utils.data.TensorDataset(x_val, y_val)
                whole = torch.utils.data.BatchSampler(torch.utils.data.SequentialSampler(ds), len(ds), drop_last=False)
                return torch.utils.data.DataLoader(ds, batch_size=None, sampler=whole)

        with tempfile.TemporaryDirectory() as tmp:
            checkpoint = ModelCheckpoint(dirpath=tmp, monitor="val_loss", mode="min", save_top_k=1, save_weights_only=True)
            trainer = L.Trainer(
                max_epochs=self.max_epochs, callbacks=[EarlyStopping("val_loss", patience=self.patience), checkpoint],
                enable_progress_bar=self.progress, enable_model_summary=False, logger=False, accelerator="cpu",
                devices=1, deterministic=True, default_root_dir=tmp, num_sanity_val_steps=0,
            )
            module = Module()
            _fit_interruptible(trainer, module, Data())
            self.epochs_trained = int(trainer.current_epoch)
            best = torch.load(Path(checkpoint.best_model_path), weights_only=True, map_location="cpu")
            state = {k.removeprefix("net."): v for k, v in best["state_dict"].items()}
            network.load_state_dict(state)
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


def _fit_interruptible(trainer, module, data) -> None:
    """``trainer.fit``, with Ctrl-C raised as ``KeyboardInterrupt`` like everywhere else.

    Lightning answers Ctrl-C with its own shutdown, which leaves SIGINT ignored and ends in
    ``sys.exit(1)``: a command interrupted during training would exit 1 without a word instead of
    saying what it kept (exit 130).
    """
    import signal
    import threading

    try:
        trainer.fit(module, datamodule=data)
    except SystemExit:
        if not trainer.interrupted:
            raise
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.default_int_handler)
        raise KeyboardInterrupt from None
