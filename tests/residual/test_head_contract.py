"""Every registered residual head through the shared contract suite (a smooth closed-form error)."""

from __future__ import annotations

import pytest

from torchcal.residual import HEADS
from torchcal.testing.head_contract import HeadContract


# the MLP trains for minutes on a loaded machine: with the slow tests
@pytest.fixture(params=[pytest.param(n, marks=pytest.mark.slow) if n == "mlp" else n for n in sorted(HEADS)])
def _registered(request):
    return request.param


class TestRegisteredHeads(HeadContract):
    @pytest.fixture(autouse=True)
    def _name(self, _registered):
        self.head_name = _registered
