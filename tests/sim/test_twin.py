"""The twin and the end-to-end acceptance of geometric calibration against its truth."""

from __future__ import annotations

import pytest

from torchcal.config.schema import RunConfig
from torchcal.instruments.tracker.run import run
from torchcal.sim.twin import Twin, TwinConfig


def test_twin_noise_matches_its_floor(generator):
    twin = Twin.create(TwinConfig(seed=1))
    q = twin.robot.sample_joints(4000, generator)
    noise = twin.measure(q, generator) - twin.true_positions(q)
    rms = float(noise.norm(dim=-1).pow(2).mean().sqrt()) * 1e3
    assert abs(rms / twin.config.noise_floor_rms_mm - 1) < 0.03


def test_non_geometric_errors_are_present_when_asked(generator):
    plain = Twin.create(TwinConfig(seed=2))
    bent = Twin.create(TwinConfig(seed=2, gravity=True, gear=True))
    q = plain.robot.sample_joints(50, generator)
    shift = (bent.true_positions(q) - plain.true_positions(q)).norm(dim=-1)
    assert float(shift.max()) > 1e-4  # > 0.1 mm somewhere


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_geometric_acceptance_on_the_twin(tmp_path, seed):
    """120 training poses, 400 test poses, tracker 0.012 + repeatability 0.008 mm per axis."""
    twin = TwinConfig(seed=seed, n_train=120, n_test=400, tracker_sigma_mm=0.012, repeatability_mm=0.008)
    config = RunConfig(name=f"geo{seed}", out=str(tmp_path), twin=twin, export=False)
    config.fit.residual = "none"
    summary = run(config)
    rms = summary["test"]["geometric"]["position_rms_mm"]
    assert rms <= 1.10 * summary["noise_floor_rms_mm"]
    assert summary["test"]["nominal"]["position_rms_mm"] > 20 * rms
    assert summary["truth_check"]["fraction_within_3_sigma"] >= 0.95
    report = (tmp_path / f"geo{seed}" / "report.md").read_text()
    assert "truth (projected)" in report and "held-out file test.csv, never fitted" in report
    assert (tmp_path / f"geo{seed}" / "figures" / "error_histogram_2.png").is_file()
