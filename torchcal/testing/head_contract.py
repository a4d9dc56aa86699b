"""The contract every residual head meets: it learns a smooth error, exports and stores what it predicts.

Run it for the registered heads (``tests/residual/test_head_contract.py`` does) or for one that lives
outside torchcal::

    from torchcal.testing.head_contract import HeadContract

    class TestMyHead(HeadContract):
        head_name = "my-head"          # its name in torchcal.residual.HEADS

The truth is closed form: a smooth function of the joints (mm) that a head must learn to well
below its spread. Needs pytest.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchcal.config.schema import FitConfig
from torchcal.residual import HEADS, ResidualHead, rms
from torchcal.residual.features import JointFeatures


def smooth_problem(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Features of ``n`` random 6-joint poses and a smooth 3-D target of them (mm)."""
    gen = torch.Generator().manual_seed(seed)
    q = (torch.rand(n, 6, generator=gen, dtype=torch.float64) * 2 - 1) * math.pi
    limits = torch.tensor([[-math.pi, math.pi]] * 6, dtype=torch.float64)
    f = JointFeatures(limits)(q)
    # low-order in the features, as a geometric fit leaves it: within reach of every kind of head
    y = torch.stack([0.3 * f[:, 0] + 0.2 * f[:, 1] * f[:, 2], 0.25 * f[:, 1] - 0.1 * f[:, 3] ** 2,
                     0.2 * f[:, 2] * f[:, 4] + 0.1 * f[:, 5]], -1)
    return f, y


_FITTED: dict[tuple[str, str], ResidualHead] = {}


class HeadContract:
    """Tests every head passes; subclasses set :attr:`head_name` (or parametrize it)."""

    head_name: str
    #: held-out RMS the head must reach, as a share of the target's own RMS
    share: float = 0.5
    #: options the suite builds the head with (small and fast)
    options = FitConfig(residual_hidden=40, mayfly_population=8, mayfly_iterations=8, seed=0, progress=False)

    @pytest.fixture
    def fitted(self) -> tuple[ResidualHead, torch.Tensor, torch.Tensor]:
        # fitted once per head and options: the tests below only read it
        key = (self.head_name, repr(self.options))
        if key not in _FITTED:
            x, y = smooth_problem(500, seed=0)
            head = HEADS[self.head_name].from_options(self.options)
            assert isinstance(head, ResidualHead) and head.name == self.head_name
            assert head.fit(x[:400], y[:400], x[400:], y[400:]) is head
            _FITTED[key] = head
        return (_FITTED[key], *smooth_problem(300, seed=1))

    def test_learns_a_smooth_error(self, fitted) -> None:
        head, x_test, y_test = fitted
        assert rms(y_test - head.predict(x_test)) < self.share * rms(y_test)

    def test_exported_module_predicts_the_same(self, fitted) -> None:
        head, x_test, _ = fitted
        with torch.no_grad():
            out = head.module().to(torch.float64)(x_test)
        assert torch.allclose(out, head.predict(x_test), rtol=0, atol=1e-12)

    def test_rebuilt_from_its_stored_state(self, fitted) -> None:
        head, x_test, _ = fitted
        rebuilt = type(head).from_state(head.settings(), head.state())
        assert torch.allclose(rebuilt.predict(x_test), head.predict(x_test), rtol=0, atol=1e-10)

    def test_refit_output_keeps_the_head_or_says_none(self, fitted) -> None:
        head, x_test, y_test = fitted
        refitted = head.refit_output(x_test, y_test)
        assert refitted is None or rms(y_test - refitted.predict(x_test)) < self.share * rms(y_test)
