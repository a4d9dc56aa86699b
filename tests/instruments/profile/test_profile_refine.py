"""Joint point-to-plane refinement: exact Jacobian, convergence, accuracy against twin truth, covariance."""

from __future__ import annotations

import math

import pytest
import torch

from torchcal.core.errors import DataError
from torchcal.instruments.profile.closed_form import closed_form
from torchcal.instruments.profile.commands import ProfileFitConfig, estimate
from torchcal.instruments.profile.model import base_points, fit_planes, rotation_angle_deg
from torchcal.instruments.profile.refine import ProfileProblem, refine
from torchcal.instruments.profile.twin import ProfileTwin, ProfileTwinConfig
from torchcal.kinematics import transforms as tf


@pytest.fixture(scope="module")
def small():
    twin = ProfileTwin(ProfileTwinConfig(seed=3, points_per_scan=30))
    return twin, twin.scan()


def test_jacobian_matches_finite_differences(small):
    twin, data = small
    T = twin.robot.flange_pose(data.q)
    problem = ProfileProblem(data, T, twin.R_design, twin.normals)
    gen = torch.Generator().manual_seed(0)
    x = problem.initial(twin.t_design, twin.offsets) + 1e-3 * torch.randn(6 + 3 * data.n_planes, generator=gen, dtype=torch.float64)
    _, jac = problem.jacobian(x)
    h = 1e-6
    fd = torch.stack([(problem.residuals(x + h * e) - problem.residuals(x - h * e)) / (2 * h) for e in torch.eye(x.numel(), dtype=torch.float64)], -1)
    assert float((jac - fd).abs().max()) < 1e-7 * float(fd.abs().max())


def test_noise_free_refinement_converges_to_truth_from_a_rough_start():
    twin = ProfileTwin(ProfileTwinConfig(seed=4, points_per_scan=30, noise_w_mm=0.0))
    data = twin.scan()
    T = twin.robot.flange_pose(data.q)
    gen = torch.Generator().manual_seed(1)
    R0 = tf.so3_exp(torch.randn(3, generator=gen, dtype=torch.float64) * math.radians(3)) @ twin.R_true
    t0 = twin.t_true + torch.tensor([0.005, -0.004, 0.006], dtype=torch.float64)
    normals, offsets, _ = fit_planes(base_points(T, data.point_scan, data.uw, R0, t0), data.point_plane(), data.n_planes)
    result = refine(data, T, R0, t0, normals, offsets)
    assert rotation_angle_deg(result.R, twin.R_true) < 1e-8
    assert float((result.t - twin.t_true).norm()) < 1e-11
    assert result.sigma_residual < 1e-12 and result.converged


@pytest.mark.parametrize("seed", [0, 1])
def test_refined_pose_meets_the_accuracy_target_and_its_sigma(seed):
    twin = ProfileTwin(ProfileTwinConfig(seed=seed))
    data = twin.scan()
    T = twin.robot.flange_pose(data.q)
    seed_result = closed_form(data, T)
    result = refine(data, T, seed_result.R, seed_result.t, seed_result.normals, seed_result.offsets)
    assert rotation_angle_deg(result.R, twin.R_true) < 0.01
    assert float((result.t - twin.t_true).norm()) * 1e3 < 0.02
    # the residual sigma is the depth noise projected on the plane normals
    assert 0.5 * 0.015 < result.sigma_residual * 1e3 < 0.015
    err = torch.cat([tf.so3_log(twin.R_true @ result.R.T), twin.t_true - result.t])
    z = err / result.covariance.diagonal()[:6].sqrt()
    assert float(z.abs().max()) < 4.5


def test_translations_only_leave_t_undetermined(small):
    twin, data = small
    sub = data.select_scans(torch.tensor([k != "rotation" for k in twin.plan.kinds]))
    T = twin.robot.flange_pose(sub.q)
    with pytest.raises(DataError, match=r"do not determine .*t_"):
        refine(sub, T, twin.R_true, twin.t_true, twin.normals, twin.offsets)


@pytest.mark.slow
def test_search_start_without_translations():
    twin = ProfileTwin(ProfileTwinConfig(seed=1, points_per_scan=100))
    data = twin.scan()
    sub = data.select_scans(torch.tensor([k != "translation" for k in twin.plan.kinds]))
    T = twin.robot.flange_pose(sub.q)
    with pytest.warns(UserWarning, match="rotation search"):
        seed, result = estimate(sub, T, ProfileFitConfig())
    assert seed is None
    assert rotation_angle_deg(result.R, twin.R_true) < 0.05
    assert float((result.t - twin.t_true).norm()) * 1e3 < 0.1
