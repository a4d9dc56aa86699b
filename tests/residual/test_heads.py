"""Residual heads: ELM closed form, MMA-ELM vs random ELM, MLP, contract, storage, gating."""

from __future__ import annotations

import math
import statistics

import pytest
import torch

from torchcal.residual import ELM, HEADS, MayflyELM, MLPHead, rms
from torchcal.residual.elm import (
    candidate_activations_t,
    solve_candidates_output_weights,
    solve_output_weights,
)
from torchcal.residual.features import JointFeatures
from torchcal.residual.selection import select_head


def _smooth_problem(n=600, seed=0):
    gen = torch.Generator().manual_seed(seed)
    limits = torch.tensor([[-math.pi, math.pi]] * 6, dtype=torch.float64)
    q = (torch.rand(n, 6, generator=gen, dtype=torch.float64) * 2 - 1) * math.pi
    y = torch.stack(
        [
            0.3 * torch.sin(2 * q[:, 0]) + 0.2 * torch.cos(q[:, 1]) * torch.sin(q[:, 2]),
            0.25 * torch.sin(q[:, 1] + q[:, 2]) + 0.1 * torch.cos(3 * q[:, 4]),
            0.2 * torch.cos(q[:, 1]) * torch.cos(q[:, 3]) - 0.15 * torch.sin(2 * q[:, 5]),
        ],
        -1,
    )
    feats = JointFeatures(limits)(q)
    return feats, y


def test_elm_output_weights_are_the_least_squares_solution():
    x, y = _smooth_problem(300)
    head = ELM(hidden=40, ridge=None).fit(x, y)
    hidden = torch.sigmoid(x @ head.weights.T + head.bias)
    assert torch.allclose(head.output, torch.linalg.lstsq(hidden, y).solution, atol=1e-8)
    assert float(head.weights.min()) >= -1 and float(head.weights.max()) <= 1
    assert float(head.bias.min()) >= 0 and float(head.bias.max()) <= 1


def test_elm_recovers_a_target_made_by_a_known_elm():
    x, _ = _smooth_problem(400)
    teacher = ELM(hidden=30, seed=5)
    teacher.weights = torch.rand(30, x.shape[1], generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 2 - 1
    teacher.bias = torch.rand(30, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    teacher.output = torch.randn(30, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    y = teacher.predict(x)
    student = ELM(hidden=30, ridge=None)
    student.set_hidden_layer(teacher.weights, teacher.bias)
    student.fit(x, y)
    assert rms(student.predict(x) - y) < 1e-8


def test_ridge_solve_matches_normal_equations():
    x, y = _smooth_problem(200)
    h = torch.sigmoid(x @ (torch.rand(20, x.shape[1], dtype=torch.float64) * 2 - 1).T)
    v = solve_output_weights(h, y, 1e-3)
    gram = h.T @ h
    lam = 1e-3 * gram.diagonal().mean()
    assert torch.allclose(v, torch.linalg.solve(gram + lam * torch.eye(20, dtype=torch.float64), h.T @ y), atol=1e-10)


@pytest.mark.parametrize("ridge", [1e-6, None])
def test_candidates_solved_together_match_each_solved_alone(ridge):
    """The Mayfly search's batched layout (one product for all candidates) is each candidate's own ELM."""
    x, y = _smooth_problem(300, seed=4)
    gen = torch.Generator().manual_seed(5)
    weights = torch.rand(7, 25, x.shape[1], generator=gen, dtype=torch.float64) * 2 - 1
    bias = torch.rand(7, 25, generator=gen, dtype=torch.float64)
    hidden_t = candidate_activations_t(x, weights, bias)
    together = solve_candidates_output_weights(hidden_t, y, ridge)
    for c in range(7):
        h = torch.sigmoid(x @ weights[c].T + bias[c])
        assert torch.allclose(hidden_t[c].T, h, rtol=0, atol=1e-14)
        alone = solve_output_weights(h, y, ridge)
        assert torch.allclose(together[c], alone, rtol=1e-9, atol=1e-12 * float(alone.abs().max()))


def test_mma_elm_beats_random_elm_of_the_same_size():
    x, y = _smooth_problem(900, seed=1)
    xt, yt = _smooth_problem(400, seed=2)
    tr, va = slice(0, 700), slice(700, 900)
    scores_mma, scores_rand = [], []
    for seed in range(3):
        mma = MayflyELM(hidden=30, population=8, iterations=15, seed=seed).fit(x[tr], y[tr], x[va], y[va])
        rnd = ELM(hidden=30, seed=seed).fit(x[tr], y[tr])
        scores_mma.append(rms(mma.predict(xt) - yt))
        scores_rand.append(rms(rnd.predict(xt) - yt))
    assert statistics.median(scores_mma) < statistics.median(scores_rand)


@pytest.mark.slow
def test_mlp_fits_the_smooth_function():
    x, y = _smooth_problem(900, seed=1)
    xt, yt = _smooth_problem(300, seed=2)
    head = MLPHead(max_epochs=150, patience=30, seed=0).fit(x[:700], y[:700], x[700:], y[700:])
    assert rms(head.predict(xt) - yt) < 0.35 * rms(yt)


def _lightning_mlp(head: MLPHead, x_train, y_train, x_val, y_val) -> torch.nn.Sequential:
    """The reference: the same training by Lightning's ``Trainer`` (seeded initialization, shuffled
    batches, Adam, plateau halving, early stopping and the best checkpoint as callbacks)."""
    import tempfile
    import warnings

    import lightning as L
    from lightning.pytorch.callbacks import EarlyStopping, ModelCheckpoint

    from torchcal.residual.mlp import make_network

    warnings.filterwarnings("ignore", message=".*(treespec|many workers).*")
    L.seed_everything(head.seed, verbose=False)
    network = make_network(x_train.shape[1], y_train.shape[1], head.width, head.depth,
                           float(y_train.std().clamp_min(1e-12))).to(x_train.dtype)

    class Module(L.LightningModule):
        def __init__(self):
            super().__init__()
            self.net = network

        def training_step(self, batch, _):
            return torch.nn.functional.mse_loss(self.net(batch[0]), batch[1])

        def validation_step(self, batch, _):
            self.log("val_loss", torch.nn.functional.mse_loss(self.net(batch[0]), batch[1]))

        def configure_optimizers(self):
            optimizer = torch.optim.Adam(self.parameters(), lr=head.learning_rate)
            plateau = torch.optim.lr_scheduler.ReduceLROnPlateau(optimizer, factor=0.5, patience=max(2, head.patience // 4))
            return {"optimizer": optimizer, "lr_scheduler": {"scheduler": plateau, "monitor": "val_loss"}}

    train = torch.utils.data.TensorDataset(x_train, y_train)
    shuffle = torch.utils.data.RandomSampler(train, generator=torch.Generator().manual_seed(head.seed))
    loader = torch.utils.data.DataLoader(train, batch_size=None,
                                         sampler=torch.utils.data.BatchSampler(shuffle, head.batch_size, drop_last=False))
    val = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(x_val, y_val), batch_size=len(x_val))
    with tempfile.TemporaryDirectory() as tmp:
        best = ModelCheckpoint(dirpath=tmp, monitor="val_loss", save_top_k=1, save_weights_only=True)
        trainer = L.Trainer(max_epochs=head.max_epochs, callbacks=[EarlyStopping("val_loss", patience=head.patience), best],
                            enable_progress_bar=False, enable_model_summary=False, logger=False, accelerator="cpu",
                            devices=1, default_root_dir=tmp, num_sanity_val_steps=0)
        trainer.fit(Module(), loader, val)
        state = torch.load(best.best_model_path, weights_only=True)["state_dict"]
    network.load_state_dict({k.removeprefix("net."): v for k, v in state.items()})
    return network


@pytest.mark.parametrize("max_epochs, patience", [(25, 40), (60, 3)])
def test_mlp_trains_exactly_as_the_lightning_trainer(max_epochs, patience):
    """The Fabric training loop against Lightning's Trainer: the same weights to the bit, whether training ran to
    ``max_epochs`` or stopped early."""
    pytest.importorskip("lightning")
    x, y = _smooth_problem(400, seed=4)
    head = MLPHead(width=16, depth=2, max_epochs=max_epochs, patience=patience, batch_size=64, seed=2)
    reference = _lightning_mlp(head, x[:300], y[:300], x[300:], y[300:])
    head.fit(x[:300], y[:300], x[300:], y[300:])
    assert (head.epochs_trained < max_epochs) == (patience < max_epochs)
    for name, value in reference.state_dict().items():
        assert torch.equal(head.module().state_dict()[name], value), name


def test_ctrl_c_during_mlp_training_is_a_keyboard_interrupt(monkeypatch):
    """Ctrl-C during training is a ``KeyboardInterrupt`` with SIGINT's handler left as it was (a trainer
    that turned it into its own shutdown and ``sys.exit(1)`` made the command exit 1 without a word);
    the command then says what it kept and exits 130."""
    import signal

    x, y = _smooth_problem(200, seed=1)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(torch.optim.Adam, "step", interrupted)
    # a command's handler, whatever an earlier test in this worker process left
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            MLPHead(max_epochs=3, patience=2, seed=0).fit(x[:150], y[:150], x[150:], y[150:])
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("name", sorted(HEADS))
def test_head_contract_and_state_round_trip(name, tmp_path):
    from torchcal.stages.residual_store import StoredResidual, load_residual, save_residual

    x, y = _smooth_problem(300)
    options = {"mlp": {"max_epochs": 5}, "mma-elm": {"hidden": 10, "population": 4, "iterations": 2}, "elm": {"hidden": 10}}[name]
    head = HEADS[name](**options).fit(x[:240], y[:240], x[240:], y[240:])
    pred = head.predict(x)
    assert pred.shape == y.shape and bool(torch.isfinite(pred).all())
    limits = torch.tensor([[-math.pi, math.pi]] * 6, dtype=torch.float64)
    features = JointFeatures(limits)
    save_residual(tmp_path, StoredResidual(head, features, {"decision": "test"}))
    loaded = load_residual(tmp_path)
    q = torch.rand(7, 6, dtype=torch.float64)
    expected = head.predict(features(q)) * 1e-3
    assert torch.allclose(loaded.predict_base_error(q), expected, atol=1e-12)
    module = loaded.to_torch_module()
    assert torch.allclose(module(q), expected, atol=1e-12)


def test_gate_rejects_heads_on_pure_noise():
    gen = torch.Generator().manual_seed(0)
    x, _ = _smooth_problem(600)
    noise = 0.01 * torch.randn(600, 3, generator=gen, dtype=torch.float64)
    selection = select_head([ELM(hidden=40), MayflyELM(hidden=20, population=4, iterations=3)], x[:480], noise[:480], x[480:], noise[480:])
    assert selection.head is None and "no residual head kept" in selection.decision
    x, y = _smooth_problem(600)
    selection = select_head([ELM(hidden=80)], x[:480], y[:480], x[480:], y[480:])
    assert selection.head is not None


def test_gate_is_not_fooled_by_a_search_that_tuned_on_the_validation_poses():
    """Few poses, pure noise: a Mayfly search tuned on the gate's own poses used to 'win' it."""
    gen = torch.Generator().manual_seed(3)
    x, _ = _smooth_problem(30)
    noise = 0.01 * torch.randn(30, 3, generator=gen, dtype=torch.float64)
    head = MayflyELM(hidden=80, population=20, iterations=50, seed=0)
    selection = select_head([head], x[:24], noise[:24], x[24:], noise[24:])
    assert selection.head is None, selection.decision


def _saved_elm(tmp_path):
    from torchcal.stages.residual_store import StoredResidual, save_residual

    x, y = _smooth_problem(200)
    head = HEADS["elm"](hidden=10).fit(x[:160], y[:160], x[160:], y[160:])
    limits = torch.tensor([[-math.pi, math.pi]] * 6, dtype=torch.float64)
    save_residual(tmp_path, StoredResidual(head, JointFeatures(limits), {"decision": "test"}))
    return tmp_path


@pytest.mark.parametrize("edit, message", [
    (lambda t, i: t.update({"head.weights": t["head.weights"].reshape(t["head.weights"].shape[1], -1).contiguous()}),
     "cannot be read"),
    (lambda t, i: t.update({"head.output": t["head.output"][:, :2].contiguous()}), "cannot be read"),
    (lambda t, i: t.update({"features.mid": t["features.mid"][:5].contiguous(),
                            "features.half_span": t["features.half_span"][:5].contiguous()}), "cannot be read"),
    (lambda t, i: t.update({"head.weights": t["head.weights"].to(torch.int64)}), "not floating point"),
    (lambda t, i: i.update({"uses_temperature": True}), "takes temperature"),
])
def test_a_tampered_head_is_one_line_naming_its_file(tmp_path, edit, message):
    """A head whose files were edited (checksums aside) is a ModelError naming the file, never a traceback
    from the first product that meets it."""
    import json

    from safetensors.torch import load_file, save_file

    from torchcal.core.errors import ModelError
    from torchcal.stages.store import _load_residual_part

    folder = _saved_elm(tmp_path)
    tensors = dict(load_file(str(folder / "residual.safetensors")))
    info = json.loads((folder / "residual.json").read_text())
    edit(tensors, info)
    save_file(tensors, str(folder / "residual.safetensors"))
    (folder / "residual.json").write_text(json.dumps(info))
    with pytest.raises(ModelError, match=message) as caught:
        _load_residual_part(folder, "cpu")
    assert "residual.json" in str(caught.value) and "\n" not in str(caught.value)


def test_half_a_head_is_refused_not_dropped(tmp_path):
    from torchcal.core.errors import ModelError
    from torchcal.stages.store import _load_residual_part

    folder = _saved_elm(tmp_path)
    (folder / "residual.json").unlink()  # the head would otherwise vanish and the model be scored without it
    with pytest.raises(ModelError, match=r"residual\.json is missing"):
        _load_residual_part(folder, "cpu")


def test_head_features_are_the_joints_only_whatever_the_file_holds():
    """A file's temperature is not a head input: the compensator and monitor take joints only (a head
    trained with it crashed every evaluation through the compensator)."""
    from torchcal.model_selection.heads import make_features
    from torchcal.sim.twin import Twin, TwinConfig

    twin = Twin.create(TwinConfig(seed=1))
    from dataclasses import replace

    data = replace(twin.sample(20, torch.Generator().manual_seed(1)), temperature=torch.linspace(20.0, 21.0, 20, dtype=torch.float64))
    features = make_features(twin.robot, data)
    assert not features.uses_temperature and features.size == 3 * twin.robot.dof
    assert torch.equal(features(data.q, data.temperature), features(data.q))
