"""First-harmonic joint errors identified with the geometry: basis, Jacobian, recovery on the twin, CV choice."""

from __future__ import annotations

import math

import pytest
import torch
from helpers import central_difference_jacobian, roundoff_atol

from torchcal.config.schema import FitConfig
from torchcal.core.errors import DataError
from torchcal.identify.calibrate import calibrate
from torchcal.identify.compliance import gravity_torque_basis
from torchcal.identify.harmonics import HARMONIC_SETS, JointHarmonics, harmonic_basis
from torchcal.identify.joint_fit import JointErrorProblem, fit_joint_errors, predicted_positions
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit, held_out_errors, save_fit
from torchcal.stages.store import load_model


def _twin_with_first_harmonics(amplitude_deg: float, seed: int = 4, last_joint: bool = False) -> Twin:
    """A twin whose gear error is a pure first harmonic ``A_j sin(q_j + phi_j)`` on joints 1..N-1 (or the last only)."""
    twin = Twin.create(TwinConfig(seed=seed, gear=True, gravity=False))
    amplitude = torch.zeros_like(twin.gear_amplitude)
    if last_joint:
        amplitude[-1, 0] = math.radians(amplitude_deg)
    else:
        amplitude[:-1, 0] = math.radians(amplitude_deg) * torch.linspace(0.6, 1.4, twin.robot.dof - 1, dtype=torch.float64)
    twin.gear_amplitude = amplitude
    return twin


def _true_coefficients(twin: Twin) -> torch.Tensor:
    """``A sin(q + phi) = A cos(phi) sin q + A sin(phi) cos q``: rows a (sin), b (cos), rad."""
    amplitude, phase = twin.gear_amplitude[:, 0], twin.gear_phase[:, 0]
    return torch.stack([amplitude * torch.cos(phase), amplitude * torch.sin(phase)])


def test_basis_is_sin_and_cos_of_each_joint_and_zero_on_the_last(robot):
    q = robot.sample_joints(40, torch.Generator().manual_seed(2))
    basis = harmonic_basis(q, HARMONIC_SETS["first"])
    assert basis.shape == (40, 2, robot.dof)
    assert torch.equal(basis[:, 0, :-1], torch.sin(q[:, :-1]))
    assert torch.equal(basis[:, 1, :-1], torch.cos(q[:, :-1]))
    assert basis[:, :, -1].abs().max() == 0.0
    harmonics = JointHarmonics(torch.ones(2, robot.dof, dtype=torch.float64))
    expected = torch.sin(q) + torch.cos(q)
    expected[:, -1] = 0.0
    assert torch.allclose(harmonics.deflection(q), expected)


def test_joint_error_jacobian_matches_central_finite_differences(robot, generator):
    twin = _twin_with_first_harmonics(0.02)
    data = twin.sample(25, generator)
    geometric = calibrate(robot, data)
    basis = torch.cat([gravity_torque_basis(robot, data.q, ("tcp",)), harmonic_basis(data.q, ("sin", "cos"))], 1)
    cols = [(0, 1), (0, 2), (1, 0), (1, 3), (2, 1), (2, 4)]  # gravity, sin and cos coefficients
    size = geometric.model.layout.size
    free = torch.cat([geometric.free[:6], torch.arange(size, size + len(cols))])
    problem = JointErrorProblem(geometric.model, data, basis, free, cols)
    xe = torch.cat([geometric.x, torch.tensor([1e-3, -2e-3, 4e-4, -3e-4, 2e-4, 5e-4], dtype=torch.float64)])
    _, jac = problem.jacobian(xe)
    numeric = central_difference_jacobian(problem.residuals, xe, free.tolist())
    assert jac[:, 6:].abs().max() > 1e-3  # the harmonic columns are not trivially zero
    assert torch.allclose(jac, numeric, rtol=1e-5, atol=roundoff_atol(float(data.position.abs().max())))


def test_injected_first_harmonic_is_recovered_within_its_sigma(generator):
    twin = _twin_with_first_harmonics(0.02)
    data = twin.sample(600, generator)
    result = fit(twin.robot, data, FitConfig(residual="none", joint_harmonics="first", progress=False))
    truth = _true_coefficients(twin)
    estimate, sigma = result.harmonics.coefficients, result.harmonics.sigma
    identified = sigma > 0
    # every joint but the last carries a harmonic the fit can see
    assert int(identified[:, :-1].sum()) >= 2 * (twin.robot.dof - 1) - 2
    assert float(sigma[identified].max()) < 0.2 * math.radians(0.02 * 0.6)
    z = ((estimate - truth)[identified] / sigma[identified]).abs()
    assert float(z.max()) < 4.0  # 10 coefficients: all within 4 sigma, most within 2
    assert float((z < 2.0).double().mean()) >= 0.7
    geometric = fit(twin.robot, data, FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none", progress=False))
    rms = {name: float((data.position - predicted_positions(r, data.q)).norm(dim=-1).pow(2).mean().sqrt())
           for name, r in (("geometric", geometric), ("harmonics", result))}
    floor = twin.config.noise_floor_rms_mm * 1e-3
    assert rms["geometric"] > 2 * floor
    assert rms["harmonics"] < 1.1 * floor


def test_last_joint_gets_no_harmonic_even_when_the_data_has_one(generator):
    twin = _twin_with_first_harmonics(0.05, last_joint=True)
    data = twin.sample(200, generator)
    result = fit(twin.robot, data, FitConfig(residual="none", joint_harmonics="first", progress=False))
    assert result.harmonics.coefficients[:, -1].abs().max() == 0.0
    assert result.harmonics.sigma[:, -1].abs().max() == 0.0


def test_model_folder_stores_and_applies_the_harmonics(tmp_path, generator):
    twin = _twin_with_first_harmonics(0.02)
    data = twin.sample(200, generator)
    result = fit(twin.robot, data, FitConfig(residual="none", joint_harmonics="first", progress=False))
    folder = save_fit(tmp_path / "model", twin.robot, data, result, {})
    stored = load_model(folder)
    assert "joint_harmonics" in stored.metadata
    errors = held_out_errors(stored, data, residual=False)
    assert torch.allclose(errors, data.position - predicted_positions(result, data.q), atol=1e-12)
    without = data.position - stored.model.tcp_position(data.q, stored.x)
    assert (without - errors).norm(dim=-1).max() > 1e-5  # the stored harmonics matter (>10 um)
    # the joint covariance travels with them: geometry first (its block is the stored covariance), then the coefficients
    n = len(stored.free)
    assert stored.joint_covariance is not None and stored.joint_coefficients is not None
    torch.testing.assert_close(stored.joint_covariance[:n, :n], stored.covariance, rtol=0, atol=0)
    sigma = stored.joint_covariance.diagonal()[n:].sqrt()
    rows, joints = stored.joint_coefficients.unbind(-1)
    torch.testing.assert_close(sigma, result.harmonics.sigma[rows, joints], rtol=1e-12, atol=0)


def test_auto_chooses_harmonics_only_when_the_cv_asks_for_them(generator):
    config = FitConfig(residual="none", gravity_compliance="none", joint_harmonics="auto", progress=False)
    with_harmonics = _twin_with_first_harmonics(0.02).sample(200, generator)
    without = _twin_with_first_harmonics(0.0).sample(200, generator)
    chosen = fit(_twin_with_first_harmonics(0.0).robot, with_harmonics, config)
    assert chosen.harmonics is not None
    assert any(n.startswith("structure chosen by 5-fold CV") and "-> geometry+harmonics" in n for n in chosen.notes)
    plain = fit(_twin_with_first_harmonics(0.0).robot, without, config)
    assert plain.harmonics is None  # nothing to gain: the simpler model within noise wins


def test_no_harmonics_on_a_joint_that_turned_through_less_than_the_minimum_range(generator):
    twin = _twin_with_first_harmonics(0.02)
    data = twin.sample(200, generator)
    narrow = data.q.clone()
    narrow[:, 1] = narrow[:, 1].mean() + 0.3 * (narrow[:, 1] - narrow[:, 1].mean()) / (narrow[:, 1].amax() - narrow[:, 1].amin())
    data = type(data)(q=narrow, position=twin.measure(narrow, generator))
    config = FitConfig(residual="none", gravity_compliance="none", joint_harmonics="first", progress=False,
                       harmonic_min_range_deg=30.0)
    result = fit(twin.robot, data, config)
    assert float(result.harmonics.coefficients[:, 1].abs().max()) == 0.0  # joint 2 spans 17 deg < 30
    assert float(result.harmonics.coefficients[:, 0].abs().max()) > 0.0
    assert any("no first harmonics on joint(s) 2" in n for n in result.notes)


def test_unknown_harmonic_option_is_a_clear_error(robot, generator):
    data = _twin_with_first_harmonics(0.0).sample(60, generator)
    with pytest.raises(DataError, match="joint_harmonics 'second'"):
        fit(robot, data, FitConfig(residual="none", joint_harmonics="second"))


def test_fit_joint_errors_without_terms_returns_the_geometry(robot, generator):
    data = _twin_with_first_harmonics(0.0).sample(60, generator)
    geometric = calibrate(robot, data)
    assert fit_joint_errors(robot, data, geometric) is geometric


def test_a_tampered_joint_covariance_is_refused(tmp_path, generator):
    from safetensors.torch import load_file, save

    from torchcal.core.errors import ModelError
    from torchcal.core.folder import write_member

    twin = _twin_with_first_harmonics(0.02)
    data = twin.sample(120, generator)
    result = fit(twin.robot, data, FitConfig(residual="none", gravity_compliance="none", joint_harmonics="first", progress=False))
    folder = save_fit(tmp_path / "model", twin.robot, data, result, {})
    tensors = load_file(str(folder / "calibration.safetensors"))
    tensors["joint_covariance"] = tensors["joint_covariance"][1:, 1:].contiguous()
    write_member(folder, "calibration.safetensors", save(tensors))  # checksums recomputed: only the shape is wrong
    with pytest.raises(ModelError, match="joint_covariance is"):
        load_model(folder)
