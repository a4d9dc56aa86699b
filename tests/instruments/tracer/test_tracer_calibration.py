"""Robot calibration from tracer lengths (joint and two-step), checked against the twin's truth."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from torchcal.data.measurements import Measurements
from torchcal.identify.calibrate import calibrate
from torchcal.instruments.tracer.data import TracerData
from torchcal.instruments.tracer.joint_fit import TracerJointProblem, calibrate_joint
from torchcal.instruments.tracer.multilateration import predict_covariance
from torchcal.instruments.tracer.twin_case import TracerTwinConfig, simulate_tracer_case
from torchcal.instruments.tracer.two_step import calibrate_two_step
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.mdh import link_transform
from torchcal.stages.geometry import registered_errors


@pytest.fixture(scope="module")
def case():
    return simulate_tracer_case(TracerTwinConfig(seed=11, n_test=150))


@pytest.fixture(scope="module")
def joint(case):
    return calibrate_joint(case.twin.robot, TracerData(case.q_train, case.lengths), sigma=case.config.sigma)


def _rms(e: torch.Tensor) -> float:
    return float(e.pow(2).sum(-1).mean().sqrt())


def _row1(x: torch.Tensor, model) -> torch.Tensor:
    """``T_base_1`` at ``q1 = 0`` of parameter vector ``x``."""
    alpha, a, beta, theta, d = x[model.layout.table_slice][:5]
    rot, pos = link_transform(alpha, a, beta, theta, d)
    return model.T_base_0 @ tf.homogeneous(rot, pos)


def test_joint_jacobian_matches_finite_differences(case, joint):
    problem = TracerJointProblem(joint.model, case.q_train[:12], case.lengths[:12],
                                 1.0 / case.config.sigma(torch.ones(12, 4, dtype=torch.float64)), torch.arange(0, 50))
    z = torch.cat([joint.x, joint.stations.reshape(-1), joint.dead_paths])
    z = z + 1e-4 * torch.randn(z.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    _, jac = problem.jacobian(z)
    h = 1e-7
    for k in [0, 1, 3, 8, 12, 27, 41, 42, 43, 45, 47, 49]:
        zp, zm = z.clone(), z.clone()
        zp[k] += h
        zm[k] -= h
        fd = (problem.residuals(zp) - problem.residuals(zm)) / (2 * h)
        col = int((problem.free == k).nonzero())
        assert torch.allclose(jac[:, col], fd, rtol=1e-5, atol=1e-6 * float(fd.abs().max()) + 1e-9), k


def test_joint_fixes_the_gauge_and_recovers_the_robot(case, joint):
    names = joint.free_names
    assert not any(n.startswith("base_") for n in names)
    assert {"alpha1", "a1", "theta1", "d1"}.isdisjoint(names)  # absorbed by the stations
    assert torch.equal(joint.model.T_reference, torch.eye(4, dtype=torch.float64))
    assert 0.7 < joint.variance_factor < 1.4
    # held-out: the calibrated model against the noise-free truth, up to a rigid motion
    pred = joint.model.tcp_position(case.test.q, joint.x)
    err = registered_errors(pred, case.test_true_base)
    nominal = registered_errors(joint.model.tcp_position(case.test.q, joint.model.nominal_vector()), case.test_true_base)
    assert _rms(nominal) > 100e-6  # the robot errors are real ...
    # ... and the lengths remove them to a fraction of the predicted multilateration point accuracy
    cov, _ = predict_covariance(case.points_train, case.stations, case.config.sigma)
    point_sigma = float(cov.diagonal()[:180].sum() / 60) ** 0.5
    assert _rms(err) < point_sigma, (_rms(err), point_sigma)


def test_joint_stations_and_dead_paths_within_three_sigma(case, joint):
    # the gauge: true row 1 replaced by nominal row 1 moves everything rigidly by G
    g = _row1(joint.x, joint.model) @ tf.invert(_row1(case.twin.x_true, case.twin.model))
    s_true = case.stations @ g[:3, :3].T + g[:3, 3]
    z = (joint.stations - s_true) / joint.station_sigmas
    assert z.abs().max() < 3.5, z
    assert ((joint.dead_paths - case.dead_paths).abs() <= 3 * joint.dead_path_sigmas).all()
    assert 0.1 < float(z.pow(2).mean()) < 3.0


def test_two_step_close_to_joint_and_to_a_comparable_tracker(case, joint):
    data = TracerData(case.q_train, case.lengths)
    two = calibrate_two_step(case.twin.robot, data, sigma=case.config.sigma)
    assert two.rows.numel() == 60 and two.calibration.sigma_residual_m < 2.0
    # a tracker whose points are as uncertain as the multilaterated ones (per-axis sigma)
    cov, _ = predict_covariance(case.points_train, case.stations, case.config.sigma)
    sigma = (cov.diagonal()[:180].reshape(60, 3).sum(-1) / 3).sqrt()
    gen = torch.Generator().manual_seed(99)
    noisy = case.points_train + torch.randn(60, 3, generator=gen, dtype=torch.float64) * sigma[:, None]
    measured = Measurements(q=case.q_train, position=noisy)
    tracker = calibrate(case.twin.robot, measured)
    tracker = calibrate(replace(case.twin.robot, tool=tracker.x[tracker.model.layout.tool_slice][:3]), measured)
    rms = {}
    for name, (model, x) in {"joint": (joint.model, joint.x), "two_step": (two.calibration.model, two.calibration.x),
                             "tracker": (tracker.model, tracker.x)}.items():
        rms[name] = _rms(registered_errors(model.tcp_position(case.test.q, x), case.test_true_base))
    assert rms["joint"] < 1.2 * rms["tracker"] and rms["two_step"] < 1.2 * rms["tracker"], rms
    # stations of the two methods agree in the base frame (to the base-frame difference of the fits)
    assert (two.stations - joint.stations).norm(dim=-1).max() < 2e-3


def test_missing_lengths_and_poses_seen_by_two_stations():
    case = simulate_tracer_case(TracerTwinConfig(seed=5, n_train=40, n_test=100, loss_probability=0.12))
    seen = torch.isfinite(case.lengths)
    assert (seen.sum(1) < 3).any() and (~seen).sum() > 10
    data = TracerData(case.q_train, case.lengths)
    joint = calibrate_joint(case.twin.robot, data, sigma=case.config.sigma)
    assert int(joint.used.sum()) == int(seen.sum())  # every length is used, two-station poses too
    err = registered_errors(joint.model.tcp_position(case.test.q, joint.x), case.test_true_base)
    assert _rms(err) < 2e-6
