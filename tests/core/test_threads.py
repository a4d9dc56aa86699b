"""core.threads: a fit's torch thread count, restored after, and the same numbers on one thread as on two."""

from __future__ import annotations

import pytest
import torch
from threadpoolctl import threadpool_info

from torchcal.core.threads import fit_threads
from torchcal.residual.elm import ELM
from torchcal.residual.mlp import MLPHead


@pytest.fixture
def two_threads():
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(previous)


def test_one_thread_inside_and_restored_after(two_threads):
    with fit_threads():
        assert torch.get_num_threads() == 1
        # numpy's BLAS and the OpenMP pool of scikit-learn's k-means too
        assert all(pool["num_threads"] == 1 for pool in threadpool_info())
    assert torch.get_num_threads() == 2


def test_restored_after_an_error(two_threads):
    with pytest.raises(RuntimeError), fit_threads():
        raise RuntimeError("inside")
    assert torch.get_num_threads() == 2


def test_never_raises_the_count(two_threads):
    torch.set_num_threads(1)
    with fit_threads(4):
        assert torch.get_num_threads() == 1


def _data(n: int = 300):
    gen = torch.Generator().manual_seed(3)
    x = torch.rand(n, 6, generator=gen, dtype=torch.float64) * 2 - 1
    y = torch.stack([torch.sin(2 * x[:, 0]) + x[:, 1] * x[:, 2], torch.cos(x[:, 3]), x[:, 4] ** 2], -1)
    return x[:240], y[:240], x[240:], y[240:]


def _weights(head) -> torch.Tensor:
    return torch.cat([v.flatten() for v in head.module().state_dict().values()])


def test_mlp_bit_identical_on_one_and_two_threads(two_threads):
    x, y, xv, yv = _data()
    two = _weights(MLPHead(max_epochs=3, patience=2, batch_size=64).fit(x, y, xv, yv))
    with fit_threads():
        one = _weights(MLPHead(max_epochs=3, patience=2, batch_size=64).fit(x, y, xv, yv))
    assert torch.equal(one, two)


def test_elm_same_to_rounding_on_one_and_two_threads(two_threads):
    x, y, _, _ = _data()
    two = _weights(ELM(hidden=80).fit(x, y))
    with fit_threads():
        one = _weights(ELM(hidden=80).fit(x, y))
    assert torch.allclose(one, two, rtol=1e-9, atol=1e-12)
