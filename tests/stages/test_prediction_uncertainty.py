"""Per-pose prediction uncertainty: closed forms for the pieces, coverage on the twin for the whole."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from torchcal.core.errors import ModelError
from torchcal.identify.uncertainty import conformal_factor, gaussian_radius_samples
from torchcal.stages.prediction_uncertainty import (
    UNCERTAINTY_FILE,
    calibrate_errors,
    load_uncertainty,
    predict,
    score,
)

# 95 % point of the chi distribution with 3 degrees of freedom: sqrt of chi-square(3)'s 7.8147
CHI3_95 = math.sqrt(7.814727903251178)


def test_conformal_factor_is_the_finite_sample_order_statistic():
    scores = torch.arange(1, 100, dtype=torch.float64)[torch.randperm(99, generator=torch.Generator().manual_seed(0))]
    assert conformal_factor(scores) == 95.0  # ceil((99 + 1) 0.95) = 95th smallest
    assert conformal_factor(torch.arange(1, 20, dtype=torch.float64)) == 19.0  # ceil(20 * 0.95) = 19
    assert conformal_factor(torch.tensor([3.0, 1.0])) == 3.0  # too few: the largest


def test_gaussian_radius_of_an_isotropic_error_is_the_chi_quantile():
    sigma = 0.02
    cov = (sigma**2 * torch.eye(3, dtype=torch.float64)).expand(4, 3, 3)
    p95 = torch.quantile(gaussian_radius_samples(cov, draws=256), 0.95, dim=1)
    # 256 draws: the 95 % point's standard error is about 3 %
    assert torch.allclose(p95, torch.full((4,), CHI3_95 * sigma, dtype=torch.float64), rtol=0.08)
    assert torch.equal(p95, p95[0].expand(4))  # the same draws for every pose: repeatable


def _synthetic(n: int, sigma_mm: float, seed: int) -> np.ndarray:
    gen = torch.Generator().manual_seed(seed)
    return (torch.randn(n, 3, generator=gen, dtype=torch.float64) * sigma_mm).norm(dim=-1).numpy()


@pytest.mark.parametrize("method", ["conformal", "gaussian"])
def test_calibrated_on_gaussian_errors_it_covers_new_ones(method):
    """Errors N(0, s^2 I), no parameter uncertainty: the discrepancy is s, and 95 % of new errors lie inside."""
    sigma_mm = 0.03
    jac = torch.zeros(2000, 3, 4, dtype=torch.float64)
    cov = torch.eye(4, dtype=torch.float64)
    calibration = calibrate_errors(jac, cov, _synthetic(2000, sigma_mm, 1), "synthetic", method)
    assert calibration.discrepancy_sigma_mm == pytest.approx(sigma_mm, rel=0.05)
    new = torch.randn(5000, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * sigma_mm * 1e-3
    prediction = predict(calibration, torch.zeros(5000, 3, 4, dtype=torch.float64), cov)
    result = score(prediction, new, "synthetic")
    assert 0.93 <= result["coverage_95"] <= 0.97
    assert result["predicted_p95_mm"] == pytest.approx(CHI3_95 * sigma_mm, rel=0.06)
    assert result["observed_p95_mm"] == pytest.approx(CHI3_95 * sigma_mm, rel=0.06)


def test_parameter_uncertainty_widens_the_region_where_the_jacobian_is_large():
    cov = torch.eye(1, dtype=torch.float64) * 1e-10  # (1e-5 m)^2
    jac = torch.zeros(2, 3, 1, dtype=torch.float64)
    jac[1, :, 0] = 10.0  # 0.1 mm per coordinate at the second pose
    calibration = calibrate_errors(torch.zeros(500, 3, 1, dtype=torch.float64), cov, _synthetic(500, 0.01, 3), "s")
    p95 = predict(calibration, jac, cov).p95_mm
    assert p95[1] > 3 * p95[0]


def test_evaluate_reports_coverage_on_the_twin(tmp_path):
    """Twin with gravity and gear errors, geometry with the joint-space terms the CV picks."""
    from torchcal.compensate.export import _expected_accuracy
    from torchcal.config.schema import FitConfig
    from torchcal.data.measurements import load_measurements
    from torchcal.instruments.tracker.evaluate import evaluate
    from torchcal.instruments.tracker.twin_case import write_twin_case
    from torchcal.kinematics.robot import load_robot
    from torchcal.sim.twin import TwinConfig
    from torchcal.stages.geometry import fit_with_selection, save_fit
    from torchcal.stages.store import load_model

    case = write_twin_case(tmp_path / "case", TwinConfig(seed=3, n_train=300, n_test=600, gravity=True, gear=True))
    robot = load_robot(case["robot.yaml"])
    train = load_measurements(case["train.csv"], robot)
    config = FitConfig(residual="none", progress=False)
    result, structure = fit_with_selection(robot, train, config)
    folder = save_fit(tmp_path / "model", robot, train, result, {}, structure=structure)
    metrics = evaluate(folder, case["test.csv"])
    assert 0.90 <= metrics["coverage_95"] <= 0.99
    assert metrics["predicted_p95_mm"] == pytest.approx(metrics["position_p95_mm"], rel=0.25)
    assert len(metrics["uncertainty"]["per_pose_predicted_p95_mm"]) == 600
    expected = _expected_accuracy(load_model(folder))
    assert expected is not None and expected["p95_mm"] == pytest.approx(metrics["predicted_p95_mm"], rel=0.1)
    # a damaged calibration is refused with the file named
    path = folder / UNCERTAINTY_FILE
    text = json.loads(path.read_text())
    text["conformal_q"] = -1
    path.write_text(json.dumps(text))
    with pytest.raises(ModelError, match=r"uncertainty.json: conformal_q"):
        load_uncertainty(folder)


def test_gaussian_radius_of_a_singular_covariance():
    """No discrepancy and one direction only: the radius is that direction's chi(1) quantile."""
    cov = torch.zeros(1, 3, 3, dtype=torch.float64)
    cov[0, 2, 2] = 0.01**2
    p95 = float(torch.quantile(gaussian_radius_samples(cov, draws=256), 0.95))
    assert p95 == pytest.approx(1.96 * 0.01, rel=0.15)  # 256 draws: about 6 % standard error here


def test_a_file_without_the_shapes_count_reads_as_its_own_or_as_unknown_after_an_update(tmp_path):
    """uncertainty.json of the version before shape_n_poses: a fit's own shape is its n_poses; an update's
    was kept from an ancestor whose count that file does not hold (it named the update's own poses)."""
    from torchcal.stages.prediction_uncertainty import ErrorCalibration

    base = {"format": "torchcal-uncertainty/1", "method": "conformal", "discrepancy_sigma_mm": 0.02, "conformal_q": 2.1,
            "score_quantiles": [0.0, 1.0, 3.0], "cv_rms_mm": 0.05, "n_poses": 150, "protocol": "5-fold CV"}
    assert ErrorCalibration.from_dict(base, tmp_path).shape_n_poses == 150
    updated = {**base, "n_poses": 12, "protocol": "leave-one-out; shape kept from the parent (its 150 out-of-fold errors)"}
    assert ErrorCalibration.from_dict(updated, tmp_path).shape_n_poses is None
    assert ErrorCalibration.from_dict({**updated, "shape_n_poses": 150}, tmp_path).shape_n_poses == 150
