"""Learned joint-space models: Fourier series of order K per joint with a smoothness prior, cubic
gravity compliance; checked against the twin's known gear errors and against finite differences."""

from __future__ import annotations

import math

import torch

from torchcal.config.schema import FitConfig
from torchcal.identify.compliance import gravity_torque_basis
from torchcal.identify.harmonics import (
    HARMONIC_SETS,
    SMOOTHNESS_SCALES_RAD,
    JointHarmonics,
    harmonic_basis,
    series_terms,
    term_order,
)
from torchcal.identify.joint_fit import LEARNED_OPTIONS, fit_joint_errors, joint_error_options
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit


def _gear_twin(orders: int, amplitude_deg: float, seed: int = 4) -> Twin:
    """Gear errors of ``orders`` harmonics on every joint but the last (the last has none: module docstring)."""
    twin = Twin.create(TwinConfig(seed=seed, gear=True, gravity=False, gear_orders=orders, gear_amplitude_deg=amplitude_deg))
    twin.gear_amplitude[-1] = 0.0
    return twin


def test_series_basis_and_slope_against_closed_form_and_finite_differences(robot):
    q = robot.sample_joints(50, torch.Generator().manual_seed(2))
    assert series_terms(3) == ("sin", "cos", "sin2", "cos2", "sin3", "cos3") == HARMONIC_SETS["fourier3"]
    assert [term_order(t) for t in series_terms(3)] == [1, 1, 2, 2, 3, 3]
    basis = harmonic_basis(q, series_terms(3))
    assert torch.equal(basis[:, 4, :-1], torch.sin(3 * q[:, :-1])) and torch.equal(basis[:, 3, :-1], torch.cos(2 * q[:, :-1]))
    assert basis[:, :, -1].abs().max() == 0.0
    coefficients = torch.randn(6, robot.dof, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 1e-3
    series = JointHarmonics(coefficients)
    assert series.order == 3 and series.set_name == "fourier3"
    a, b = coefficients[0::2, 0], coefficients[1::2, 0]
    k = torch.arange(1, 4, dtype=torch.float64)
    expected = (a * torch.sin(k * q[:, :1]) + b * torch.cos(k * q[:, :1])).sum(1)
    assert torch.allclose(series.deflection(q)[:, 0], expected, rtol=0, atol=1e-15)
    h = 1e-6
    fd = (series.deflection(q + h) - series.deflection(q - h)) / (2 * h)
    assert torch.allclose(series.slope(q), fd, rtol=0, atol=1e-11)


def test_cubic_compliance_basis_is_the_tcp_torque_cubed(robot):
    q = robot.sample_joints(30, torch.Generator().manual_seed(5))
    basis = gravity_torque_basis(robot, q, ("tcp", "tcp3"))
    assert float(basis[:, 0].abs().max()) > 0.1  # m: levers of the twin arm
    assert torch.allclose(basis[:, 1], basis[:, 0] ** 3, rtol=0, atol=1e-15)


def test_extended_prior_holds_the_given_sigmas_and_none_elsewhere(robot, generator):
    data = _gear_twin(2, 0.0).sample(60, generator)
    result = fit(robot, data, FitConfig(residual="none", uncertainty="none", gravity_compliance="none",
                                        joint_harmonics="none", progress=False))
    prior = result.prior
    k = len(prior.names)
    free = torch.cat([prior.free, torch.tensor([result.model.layout.size, result.model.layout.size + 1])])
    sigma = torch.tensor([2e-4, math.inf], dtype=torch.float64)
    ext = prior.extended(free, 2, result.model.layout.size + 2, sigma)
    assert math.isclose(float(ext.precision[k, k]), 2e-4**-2, rel_tol=1e-12) and float(ext.precision[k + 1, k + 1]) == 0.0
    assert torch.allclose(ext.sqrt_precision.T @ ext.sqrt_precision, ext.precision)
    assert torch.equal(ext.precision[:k, :k], prior.precision)


def test_series_of_order_three_is_learned_through_the_kinematics(generator):
    """The twin's gear error of three harmonics, recovered as a curve: the learned dq_j(q_j) against the
    truth over each joint's range, to well under the error's own size."""
    twin = _gear_twin(3, 0.02)
    data = twin.sample(800, generator)
    result = fit(twin.robot, data, FitConfig(residual="none", uncertainty="none", gravity_compliance="none",
                                             joint_harmonics="fourier3", progress=False))
    assert result.harmonics.order == 3 and result.harmonics.prior_scale_rad in SMOOTHNESS_SCALES_RAD
    q = twin.robot.sample_joints(2000, torch.Generator().manual_seed(9))
    truth, learned = twin.gear_deviation(q), result.harmonics.deflection(q)
    for j in range(twin.robot.dof - 1):
        # a constant is the joint offset's (theta_j), not the series': compare the shapes
        miss = (learned[:, j] - truth[:, j]) - (learned[:, j] - truth[:, j]).mean()
        size = truth[:, j] - truth[:, j].mean()
        assert float(miss.pow(2).mean().sqrt()) < 0.15 * float(size.pow(2).mean().sqrt()), j
    # first harmonics alone leave the higher orders in the data
    first = fit(twin.robot, data, FitConfig(residual="none", uncertainty="none", gravity_compliance="none",
                                            joint_harmonics="first", progress=False))
    test = twin.sample(400, generator)
    from torchcal.identify.joint_fit import predicted_positions

    rms = {name: float((test.position - predicted_positions(r, test.q)).norm(dim=-1).pow(2).mean().sqrt())
           for name, r in (("series", result), ("first", first))}
    floor = twin.config.noise_floor_rms_mm * 1e-3
    assert rms["series"] < 1.2 * floor < rms["first"]


def test_evidence_shrinks_the_series_where_the_data_has_none(robot, generator):
    """No gear error: the evidence picks the smallest prior scale and the series stays small;
    a 0.02 deg gear error: a larger scale."""
    scales = {}
    for amplitude in (0.0, 0.02):
        twin = _gear_twin(3, amplitude)
        data = twin.sample(400, generator)
        geometric = fit(twin.robot, data, FitConfig(residual="none", uncertainty="none", gravity_compliance="none",
                                                    joint_harmonics="none", progress=False))
        result = fit_joint_errors(twin.robot, data, geometric, (), HARMONIC_SETS["fourier3"])
        scales[amplitude] = result.harmonics.prior_scale_rad
    assert scales[0.0] == min(SMOOTHNESS_SCALES_RAD)
    assert scales[0.02] > scales[0.0]


def test_auto_options_put_the_learned_models_last():
    options = joint_error_options("auto", "auto")
    classic = ("none", "wrist", "elbow+wrist", "elbow+forearm+wrist")
    assert options[:8] == [(g, h) for h in ("none", "first") for g in classic]
    assert options[8:] == list(LEARNED_OPTIONS)
    assert joint_error_options("wrist", "auto") == [("wrist", "none"), ("wrist", "first"), ("wrist", "fourier2")]
    assert joint_error_options("auto", "fourier3") == [(g, "fourier3") for g in classic]
    assert joint_error_options("elbow+wrist+cubic", "first") == [("elbow+wrist+cubic", "first")]
    assert joint_error_options("none", "fourier2") == [("none", "fourier2")]


def _auto(**kwargs) -> FitConfig:
    return FitConfig(residual="none", uncertainty="none", progress=False, **kwargs)


def test_gate_keeps_the_learned_model_where_the_twin_has_higher_gear_orders_and_it_wins_on_blocks(generator):
    twin = Twin.create(TwinConfig(seed=3, gravity=True, gear=True, gear_orders=3, gear_amplitude_deg=0.02,
                                  compliance_cubic=0.5))
    data = twin.sample(600, generator)
    result = fit(twin.robot, data, _auto())
    note = next(n for n in result.notes if n.startswith("structure chosen"))
    assert result.harmonics is not None and result.harmonics.order > 1, note
    assert "wins on blocks of measurement order too" in note


def test_gate_falls_back_to_the_classic_structure_when_blocks_refuse_the_learned_one(generator, monkeypatch):
    """The same twin; the blocks CV is made to prefer the classic rival (its learned errors doubled): the
    fit then carries the classic structure and says why."""
    import torchcal.stages.geometry as geometry
    from torchcal.model_selection.compare import compare_candidates

    original = geometry.cross_validate_structures

    def blocks_prefer_the_rival(robot, data, fit_geometry, options, folds, **kwargs):
        out = original(robot, data, fit_geometry, options, folds, **kwargs)
        if len(options) == 2:  # the blocks check: the classic rival, then the learned model
            for c in out.candidates[1:]:
                c.errors_mm = c.errors_mm * 2.0
            out.comparison = compare_candidates(out.candidates, folds.units(), folds.description)
        return out

    monkeypatch.setattr(geometry, "cross_validate_structures", blocks_prefer_the_rival)
    twin = Twin.create(TwinConfig(seed=3, gravity=True, gear=True, gear_orders=3, gear_amplitude_deg=0.02,
                                  compliance_cubic=0.5))
    data = twin.sample(600, generator)
    result = fit(twin.robot, data, _auto())
    note = next(n for n in result.notes if n.startswith("structure chosen"))
    assert result.harmonics is None or result.harmonics.order == 1, note
    assert "refused on blocks of measurement order" in note
