"""A head rebuilt from its stored settings and state describes itself as the original did."""

import torch

from torchcal.residual import HEADS
from torchcal.residual.mlp import MLPHead, make_network


def test_restored_mlp_reports_its_settings():
    settings = {"width": 8, "depth": 2, "n_in": 4, "n_out": 3, "seed": 0, "output_scale": 2.5}
    network = make_network(4, 3, 8, 2, 2.5).to(torch.float64)
    head = MLPHead.from_state(settings, network.state_dict())
    assert head.settings() == settings  # output_scale was lost: settings() raised AttributeError
    again = MLPHead.from_state(head.settings(), head.state())
    x = torch.rand(5, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    assert torch.equal(again.predict(x), head.predict(x))


def test_restored_elm_heads_round_trip():
    gen = torch.Generator().manual_seed(1)
    x, y = torch.rand(40, 4, generator=gen, dtype=torch.float64), torch.rand(40, 3, generator=gen, dtype=torch.float64)
    for name in ("elm", "mma-elm"):
        kwargs = {"hidden": 6} if name == "elm" else {"hidden": 6, "population": 4, "iterations": 2}
        head = HEADS[name](**kwargs).fit(x[:30], y[:30], x[30:], y[30:])
        again = HEADS[name].from_state(head.settings(), head.state())
        assert again.settings() == head.settings()
        assert torch.equal(again.predict(x), head.predict(x))
