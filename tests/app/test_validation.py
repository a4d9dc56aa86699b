"""Validation protocols through the fit/evaluate pipeline, on a twin case laid out like a real set."""

from __future__ import annotations

import pytest

from torchcal.app.validation import STAGES, Protocol, run_protocol
from torchcal.instruments.tracker.twin_case import write_twin_case
from torchcal.sim.twin import TwinConfig


@pytest.mark.slow
def test_cv_protocol_reaches_the_twin_noise_floor_and_covers_95_percent(tmp_path):
    config = TwinConfig(seed=3, n_train=150, n_test=10)
    write_twin_case(tmp_path / "twin-set", config)  # robot.yaml + train.csv, as a real set
    protocol = Protocol("twin-set", "grouped 5-fold CV", "train.csv")
    result = run_protocol(tmp_path, protocol, residual=False)
    assert set(result["stages"]) == set(STAGES)
    geo = result["stages"]["geometry only"]
    assert geo["n_poses"] == 150
    floor = config.noise_floor_rms_mm
    # held-out RMS of a correct geometric model: the noise floor plus the parameter-estimation share,
    # larger than on random folds since whole configuration regions are held out
    assert floor < geo["position_rms_mm"] < 1.5 * floor
    assert result["stages"]["nominal (registered)"]["position_rms_mm"] > 5 * floor
    for method in ("conformal", "gaussian"):  # the fold's fits calibrate on their own inner CV
        assert 0.85 < geo["uncertainty"][method]["coverage_95"] <= 1.0
    # no compliance in this twin: the default fit's own CV has nothing to gain from it on most folds
    assert result["stages"]["default fit"]["position_rms_mm"] < 1.1 * geo["position_rms_mm"]
