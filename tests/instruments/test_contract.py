"""Every registered instrument through the shared contract suite (simulate -> recognise -> load -> fit -> evaluate)."""

from __future__ import annotations

import pytest

from torchcal.instruments.registry import names
from torchcal.testing.instrument_contract import InstrumentContract


@pytest.fixture(params=names())
def _registered(request):
    return request.param


class TestRegisteredInstruments(InstrumentContract):
    @pytest.fixture(autouse=True)
    def _name(self, _registered):
        self.instrument_name = _registered
