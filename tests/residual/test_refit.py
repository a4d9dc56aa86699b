"""After the gate: the kept head is refitted on training + validation poses, tuning slice unchanged."""

import torch

from torchcal.residual import ELM
from torchcal.residual.base import ResidualHead
from torchcal.residual.selection import refit_on_all, tuning_split


class RecordingHead(ResidualHead):
    """A head that steers itself with its validation pair and records what it was given."""

    name = "recording"

    def fit(self, x_train, y_train, x_val, y_val):
        self.seen = (x_train.clone(), x_val.clone())
        self.mean = y_train.mean(0)
        return self

    def module(self):
        mean = self.mean

        class Constant(torch.nn.Module):
            def forward(self, x):
                return mean.expand(x.shape[0], -1)

        return Constant()

    def settings(self):
        return {}


def _data(n, seed):
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 4, generator=gen, dtype=torch.float64)
    y = torch.stack([torch.sin(3 * x[:, 0]), x[:, 1] * x[:, 2], torch.cos(x[:, 3])], -1)
    return x, y


def test_tuning_head_gets_fit_plus_validation_and_the_same_tuning_slice():
    x, y = _data(100, 0)
    xv, yv = _data(25, 1)
    head = refit_on_all(RecordingHead(), x, y, xv, yv, seed=3)
    fit_idx, tune_idx = tuning_split(100, seed=3)
    seen_fit, seen_tune = head.seen
    torch.testing.assert_close(seen_tune, x[tune_idx])
    torch.testing.assert_close(seen_fit, torch.cat([x[fit_idx], xv]))
    # no tuning pose leaks into the fit
    assert not (seen_fit[:, None, :] == seen_tune[None, :, :]).all(-1).any()


def test_plain_elm_refit_equals_a_fit_on_all_poses():
    x, y = _data(120, 2)
    xv, yv = _data(30, 3)
    refitted = refit_on_all(ELM(hidden=20, seed=4), x, y, xv, yv, seed=0)
    direct = ELM(hidden=20, seed=4).fit(torch.cat([x, xv]), torch.cat([y, yv]), xv, yv)
    xt, _ = _data(50, 5)
    torch.testing.assert_close(refitted.predict(xt), direct.predict(xt))


def test_mma_elm_refit_keeps_the_searched_hidden_layer():
    from torchcal.residual import MayflyELM

    x, y = _data(120, 6)
    xv, yv = _data(30, 7)
    head = MayflyELM(hidden=10, population=4, iterations=3, seed=1)
    fit_idx, tune_idx = tuning_split(120, seed=0)
    head.fit(x[fit_idx], y[fit_idx], x[tune_idx], y[tune_idx])
    w, b = head.elm.weights.clone(), head.elm.bias.clone()
    refit_on_all(head, x, y, xv, yv, seed=0)
    torch.testing.assert_close(head.elm.weights, w)
    torch.testing.assert_close(head.elm.bias, b)
    direct = ELM(hidden=10, seed=1)
    direct.set_hidden_layer(w, b)
    direct.fit(torch.cat([x, xv]), torch.cat([y, yv]))
    torch.testing.assert_close(head.predict(xv), direct.predict(xv))


def test_mma_elm_refit_before_fit_is_refused():
    import pytest

    from torchcal.residual import MayflyELM

    x, y = _data(40, 8)
    with pytest.raises(RuntimeError, match="call fit first"):
        refit_on_all(MayflyELM(hidden=5, population=2, iterations=1), x, y, x, y)
