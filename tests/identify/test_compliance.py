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


def _nominal_axes_and_origins(robot, q):
    """Joint axes and origins ``(B, N, 3)`` of the nominal chain at ``q``, ``base`` frame, and the nominal TCP ``(B, 3)``."""
    from torchcal.kinematics.mdh import chain_frames

    model = ErrorModel(robot)
    x = model.nominal_vector()
    t0 = model.T_base_0
    frames = chain_frames(q, model.table(x), r_start=t0[:3, :3], p_start=t0[:3, 3])
    return frames.stacked("z"), frames.stacked("o"), model.tcp_position(q, x)


def _unit_weight_torque(axis, lever):
    """``tau = z . (r x (-e_z)) = -(z x r) . e_z``, written out per component (m per unit weight)."""
    return -(axis[:, 0] * lever[:, 1] - axis[:, 1] * lever[:, 0])


def test_basis_is_the_torque_of_a_unit_weight_by_closed_form(robot):
    """Joint 1 (vertical axis) carries no gravity torque; joint 2 carries the horizontal lever of the TCP."""
    q = robot.sample_joints(50, torch.Generator().manual_seed(1))
    basis = gravity_torque_basis(robot, q, ("tcp",))[:, 0]
    assert basis[:, 0].abs().max() < 1e-12
    axes, origins, tcp = _nominal_axes_and_origins(robot, q)
    expected = _unit_weight_torque(axes[:, 1], tcp - origins[:, 1])
    assert torch.allclose(basis[:, 1], expected, atol=1e-12)


def test_forearm_basis_is_the_torque_of_a_unit_weight_at_the_wrist_centre_on_joints_1_to_3(robot):
    """The forearm weight sits at the origin of MDH frame 5 and loads joints 1-3 only (beyond it, nothing)."""
    q = robot.sample_joints(50, torch.Generator().manual_seed(2))
    basis = gravity_torque_basis(robot, q, ("elbow", "forearm", "tcp"))
    axes, origins, _ = _nominal_axes_and_origins(robot, q)
    wrist_centre = origins[:, 4]
    for j in (1, 2):  # joints 2 and 3
        expected = _unit_weight_torque(axes[:, j], wrist_centre - origins[:, j])
        assert float(expected.abs().max()) > 0.1  # a real lever here (m)
        assert torch.allclose(basis[:, 1, j], expected, atol=1e-12)
    assert basis[:, 1, 3:].abs().max() == 0.0  # the wrist joints carry the tcp weight, not the forearm's
    assert basis[:, 0, 2:].abs().max() == 0.0  # and the elbow weight loads joints 1-2 only, as before


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


def test_the_twins_forearm_weight_needs_the_forearm_point():
    """The twin's arm carries point masses at the middle of the upper arm, the middle of the forearm and the
    wrist (sim.twin): the elbow and TCP points cannot express the forearm's, whose lever does not turn with
    the wrist; with the forearm point the fit reaches the twin's noise floor on new poses."""
    from torchcal.config.schema import FitConfig
    from torchcal.sim.twin import Twin, TwinConfig
    from torchcal.stages.geometry import fit

    twin = Twin.create(TwinConfig(seed=0, gravity=True))
    gen = torch.Generator().manual_seed(5)
    train, test = twin.sample(300, gen), twin.sample(400, gen)
    held_out = {}
    for points in ("elbow+wrist", "elbow+forearm+wrist"):
        result = fit(twin.robot, train, FitConfig(residual="none", uncertainty="none", progress=False,
                                                  gravity_compliance=points, joint_harmonics="none"))
        error = test.position - predicted_positions(result, test.q)
        held_out[points] = float(error.norm(dim=-1).pow(2).mean().sqrt()) * 1e3
    floor = twin.config.noise_floor_rms_mm
    assert held_out["elbow+forearm+wrist"] < 1.1 * floor, (held_out, floor)
    assert held_out["elbow+wrist"] > 1.2 * floor, (held_out, floor)
