"""Every registered residual head through the shared contract suite (a smooth closed-form error)."""

from __future__ import annotations

import pytest

from torchcal.residual import HEADS
from torchcal.testing.head_contract import HeadContract

#: heads that do not learn the contract's smooth error clearly better than an affine least-squares fit
#: of the same features (held-out RMS, contract options: elm 1.08x, mma-elm 0.90x that fit's; the bar
#: is 0.5x). A known shortfall of the random / searched sigmoid layer at this size, recorded here
#: rather than hidden by a bar that the affine fit already passes: strict, so that a head which
#: starts to pass is noticed.
BELOW_AFFINE_BAR = {"elm", "mma-elm"}


# the MLP trains for minutes on a loaded machine: with the slow tests
@pytest.fixture(params=[pytest.param(n, marks=pytest.mark.slow) if n == "mlp" else n for n in sorted(HEADS)])
def _registered(request):
    return request.param


class TestRegisteredHeads(HeadContract):
    @pytest.fixture(autouse=True)
    def _name(self, _registered, request):
        self.head_name = _registered
        if request.node.originalname == "test_learns_a_smooth_error" and _registered in BELOW_AFFINE_BAR:
            request.applymarker(pytest.mark.xfail(strict=True, reason=(
                f"{_registered} does not beat the affine least-squares fit of its features by 2x")))
