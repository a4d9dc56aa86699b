"""Every registered metaheuristic through the shared contract suite (closed-form sphere in a box)."""

from __future__ import annotations

import pytest

from torchcal.optimize import OPTIMIZERS
from torchcal.testing.metaheuristic_contract import MetaheuristicContract

#: a budget of about 2000 evaluations each
SETTINGS = {"mayfly": {"population": 20, "iterations": 50}, "random": {"evaluations": 2000, "batch": 40}}


def test_every_registered_optimizer_has_contract_settings():
    assert set(SETTINGS) == set(OPTIMIZERS)


@pytest.fixture(params=sorted(OPTIMIZERS))
def _registered(request):
    return request.param


class TestRegisteredOptimizers(MetaheuristicContract):
    @pytest.fixture(autouse=True)
    def _name(self, _registered):
        self.name = _registered

    def make(self):
        return OPTIMIZERS[self.name](**SETTINGS[self.name])
