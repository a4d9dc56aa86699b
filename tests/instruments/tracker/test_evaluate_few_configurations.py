"""``evaluate`` on few distinct joint configurations: what a frame or tool fitted to them can say."""

from __future__ import annotations

import warnings

import pytest
import torch

from torchcal.config.schema import FitConfig
from torchcal.core.errors import DataError
from torchcal.data.measurements import Measurements
from torchcal.instruments.tracker.evaluate import score
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit, save_fit
from torchcal.stages.store import load_model


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    twin = Twin.create(TwinConfig(seed=4, gravity=False, gear=False))
    train = twin.sample(80, torch.Generator().manual_seed(1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        config = FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none", progress=False)
        folder = save_fit(tmp_path_factory.mktemp("few") / "m", twin.robot, train, fit(twin.robot, train, config), {})
    return twin, load_model(folder)


def _repeated(twin: Twin, n_configurations: int, repeats: int) -> Measurements:
    """``repeats`` noisy measurements of each of ``n_configurations`` joint configurations."""
    generator = torch.Generator().manual_seed(9)
    q = twin.robot.sample_joints(n_configurations, generator).repeat(repeats, 1)
    return Measurements(q=q, position=twin.measure(q, generator), source="few.csv")


def test_register_counts_configurations_not_rows(fitted):
    twin, stored = fitted
    with pytest.raises(DataError, match=r"1 distinct joint configurations \(20 poses\) cannot check it"):
        score(stored, _repeated(twin, 1, 20), register=True, corrections=False)
    with pytest.warns(UserWarning, match=r"--register fitted 6 frame parameters to 5 distinct joint configurations"):
        score(stored, _repeated(twin, 5, 4), register=True, corrections=False)


def test_a_nominal_fitted_to_too_few_configurations_is_no_comparison(fitted):
    twin, stored = fitted
    with pytest.warns(UserWarning, match="its figure is no comparison"):
        metrics = score(stored, _repeated(twin, 1, 1), corrections=False).metrics
    assert "no comparison" in metrics["nominal"]["protocol"] and any("no comparison" in w for w in metrics["warnings"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # twelve configurations: a comparison, no warning
        metrics = score(stored, _repeated(twin, 12, 1), corrections=False, leakage=False).metrics
    assert "no comparison" not in metrics["nominal"]["protocol"]


def test_repeats_read_back_with_encoder_jitter_are_one_configuration(fitted):
    twin, stored = fitted
    data = _repeated(twin, 1, 20)
    jitter = (torch.rand(data.q.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64) - 0.5) * 4e-5
    jittered = Measurements(q=data.q + jitter, position=data.position, source="jitter.csv")
    with pytest.raises(DataError, match=r"1 distinct joint configurations \(20 poses\)"):
        score(stored, jittered, register=True, corrections=False)
