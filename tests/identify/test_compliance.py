"""Gravity compliance identified with the geometry: torque basis, Jacobian, recovery on synthetic data."""

from __future__ import annotations

import math

import torch
from helpers import central_difference_jacobian, roundoff_atol

from tests.conftest import perturbed_vector
from torchcal.data.measurements import Measurements
from torchcal.identify.calibrate import calibrate
from torchcal.identify.compliance import GravityCompliance, gravity_torque_basis
from torchcal.identify.joint_fit import JointErrorProblem, fit_with_compliance, predicted_positions
from torchcal.kinematics.error_model import ErrorModel


def _synthetic(robot, generator, n, coefficients, points=("elbow", "tcp"), noise_mm=0.0):
    """Positions of a perturbed robot whose joints sag by ``c * tau`` (the model itself is the truth)."""
    truth = ErrorModel(robot)
    x_true = perturbed_vector(truth, generator)
    q = robot.sample_joints(n, generator)
    sag = GravityCompliance(points, coefficients)
    position = truth.tcp_position(sag.effective_joints(robot, q), x_true)
    position = position + noise_mm * 1e-3 * torch.randn(position.shape, generator=generator, dtype=torch.float64)
    return Measurements(q=q, position=position), truth, x_true


def test_basis_is_the_torque_of_a_unit_weight_by_closed_form(robot):
    """Joint 1 (vertical axis) carries no gravity torque; joint 2 carries the horizontal lever of the TCP."""
    q = robot.sample_joints(50, torch.Generator().manual_seed(1))
    basis = gravity_torque_basis(robot, q, ("tcp",))[:, 0]
    assert basis[:, 0].abs().max() < 1e-12
    model = ErrorModel(robot)
    x = model.nominal_vector()
    from torchcal.kinematics.mdh import chain_frames

    t0 = model.T_base_0
    frames = chain_frames(q, model.table(x), r_start=t0[:3, :3], p_start=t0[:3, 3])
    axis, origin = frames.stacked("z")[:, 1], frames.stacked("o")[:, 1]
    lever = model.tcp_position(q, x) - origin
    # tau = z . (r x (-e_z)) = -(z x r) . e_z ... written out per component
    expected = -(axis[:, 0] * lever[:, 1] - axis[:, 1] * lever[:, 0])
    assert torch.allclose(basis[:, 1], expected, atol=1e-12)


def test_compliant_jacobian_matches_finite_differences(robot, generator):
    data, _, _ = _synthetic(robot, generator, 20, torch.zeros(2, robot.dof))
    geometric = calibrate(robot, data)
    basis = gravity_torque_basis(robot, data.q, ("elbow", "tcp"))
    cols = [(0, 1), (1, 1), (1, 2), (1, 4)]
    size = geometric.model.layout.size
    free = torch.cat([geometric.free[:5], torch.arange(size, size + len(cols))])
    problem = JointErrorProblem(geometric.model, data, basis, free, cols)
    xe = torch.cat([geometric.x, torch.tensor([1e-3, 2e-3, -1e-3, 5e-3], dtype=torch.float64)])
    _, jac = problem.jacobian(xe)
    numeric = central_difference_jacobian(problem.residuals, xe, free.tolist())
    assert torch.allclose(jac, numeric, rtol=1e-5, atol=roundoff_atol(float(data.position.abs().max())))


def test_recovers_the_sag_that_geometry_cannot_express(robot, generator):
    # rad per metre of unit-weight lever: ~0.1-0.3 mrad of sag at arm's length
    coefficients = torch.zeros(2, robot.dof, dtype=torch.float64)
    coefficients[0, 1] = 2e-4
    coefficients[1, 1:5] = torch.tensor([4e-4, 5e-4, 3e-4, 6e-4], dtype=torch.float64)
    data, _, _ = _synthetic(robot, generator, 300, coefficients, noise_mm=0.002)
    geometric = calibrate(robot, data)
    joint = fit_with_compliance(robot, data, geometric, ("elbow", "tcp"))
    geo_rms = float((data.position - predicted_positions(geometric, data.q)).norm(dim=-1).pow(2).mean().sqrt())
    joint_rms = float((data.position - predicted_positions(joint, data.q)).norm(dim=-1).pow(2).mean().sqrt())
    noise_rms = math.sqrt(3) * 0.002e-3
    assert geo_rms > 5 * noise_rms  # the sag is visible to geometry alone
    assert joint_rms < 1.5 * noise_rms  # and the joint fit explains it down to the noise
    # the joint-2..5 coefficients of the TCP weight are recovered (joint 6 carries no independent sag here)
    assert torch.allclose(joint.compliance.coefficients[1, 1:4], coefficients[1, 1:4], rtol=0.05, atol=2e-5)
