"""MAP identification with a prior: closed forms, unseen directions, coverage on twins, overrides."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace

import numpy as np
import pytest
import torch

from torchcal.core.errors import DataError, ModelError
from torchcal.identify.calibrate import calibrate
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.prior import (
    PriorProblem,
    PriorSpec,
    Tolerances,
    parameter_kind,
    posterior_covariance,
    prior_table,
    resolve_tolerances,
    solve_map,
)
from torchcal.sim.twin import Twin, TwinConfig


@dataclass
class LinearProblem:
    """``r = y - A x[free]``: a linear least-squares problem with the identifier's interface."""

    a: torch.Tensor
    y: torch.Tensor
    free: torch.Tensor

    @property
    def names(self) -> list[str]:
        return [f"p{i}" for i in self.free.tolist()]

    def residuals(self, x: torch.Tensor) -> torch.Tensor:
        return self.y - self.a @ x[self.free]

    def jacobian(self, x: torch.Tensor, columns: torch.Tensor | None = None):
        cols = self.free if columns is None else columns
        pos = [self.free.tolist().index(c) for c in cols.tolist()]
        return self.residuals(x), -self.a[:, pos]


def _prior(k: int, mean: torch.Tensor, sigma: torch.Tensor):
    spec = PriorSpec()
    from torchcal.identify.prior import Prior

    precision = torch.diag(torch.where(torch.isfinite(sigma), 1 / sigma**2, 0.0))
    return Prior(names=[f"p{i}" for i in range(k)], free=torch.arange(k), mean=mean, sqrt_precision=precision.sqrt(),
                 precision=precision, sigma=sigma, tolerance_sigma=sigma, spec=spec)


def test_stacked_problem_gives_the_closed_form_posterior_mean_and_covariance():
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(40, 4, generator=gen, dtype=torch.float64)
    y = torch.randn(40, generator=gen, dtype=torch.float64)
    mean = torch.tensor([0.3, -0.2, 0.0, 1.0], dtype=torch.float64)
    sigma = torch.tensor([0.1, 1.0, math.inf, 0.05], dtype=torch.float64)
    prior = _prior(4, mean, sigma)
    problem = LinearProblem(a, y, torch.arange(4))
    s = 0.7
    x = LevenbergMarquardt().solve(PriorProblem(problem, prior, s), torch.zeros(4, dtype=torch.float64)).x
    lam = prior.precision
    h = a.T @ a / s**2 + lam
    expected = torch.linalg.solve(h, a.T @ y / s**2 + lam @ mean)
    assert torch.allclose(x, expected, atol=1e-9)
    r, jac = problem.jacobian(x)
    cov, p_eff = posterior_covariance(jac, r, lam, s)
    assert torch.allclose(cov, torch.linalg.inv(h), rtol=1e-8)
    assert 0 < p_eff < 4


def test_a_direction_the_data_cannot_see_stays_at_the_prior_with_its_sigma():
    gen = torch.Generator().manual_seed(1)
    a = torch.randn(30, 3, generator=gen, dtype=torch.float64)
    a[:, 2] = a[:, 1]  # p1 and p2 act alike: only their sum is seen
    truth = torch.tensor([1.0, 0.4, 0.0], dtype=torch.float64)
    y = a @ truth + 0.01 * torch.randn(30, generator=gen, dtype=torch.float64)
    prior = _prior(3, torch.zeros(3, dtype=torch.float64), torch.tensor([10.0, 1.0, 1.0], dtype=torch.float64))
    fit = solve_map(LinearProblem(a, y, torch.arange(3)), prior, torch.zeros(3, dtype=torch.float64), LevenbergMarquardt())
    assert abs(float(fit.x[0]) - 1.0) < 0.02
    assert abs(float(fit.x[1] + fit.x[2]) - 0.4) < 0.02
    assert abs(float(fit.x[1] - fit.x[2])) < 1e-6  # the unseen difference stays at the prior's 0
    sd = fit.covariance.diagonal().sqrt()
    # along the unseen direction (1, -1)/sqrt 2 the posterior keeps the prior's sigma (1)
    d = torch.tensor([0.0, 1.0, -1.0], dtype=torch.float64) / 2**0.5
    assert abs(float(d @ fit.covariance @ d) ** 0.5 - 1.0) < 1e-6
    assert float(sd[0]) < 0.01
    assert abs(fit.noise_sigma - 0.01) < 0.004  # the data's own noise, re-estimated


def test_parameter_kinds():
    assert [parameter_kind(n) for n in ("a2", "d6", "alpha3", "beta2", "theta1", "tool_z", "tool_ry", "base_x")] == [
        "length_mm", "length_mm", "angle_deg", "angle_deg", "joint_offset_deg", "tool_mm", "tool_deg", None]


def test_robot_file_and_options_override_the_defaults(tmp_path):
    path = tmp_path / "robot.yaml"
    path.write_text("name: r\ncalibration_prior: {length_mm: 2.0, joint_offset_deg: 0.3}\nkinematics: {}\n")
    tol = resolve_tolerances(str(path), {"joint_offset_deg": 0.5, "tool_mm": None})
    assert (tol.length_mm, tol.joint_offset_deg, tol.angle_deg, tol.tool_mm) == (2.0, 0.5, Tolerances().angle_deg,
                                                                               Tolerances().tool_mm)
    path.write_text("name: r\ncalibration_prior: {length_mm: 2e0}\nkinematics: {}\n")  # YAML 1.1 reads 2e0 as text
    assert resolve_tolerances(str(path)).length_mm == 2.0
    path.write_text("name: r\ncalibration_prior: {lenght_mm: 2.0}\nkinematics: {}\n")
    with pytest.raises(ModelError, match="lenght_mm"):
        resolve_tolerances(str(path))
    with pytest.raises(ModelError, match="positive"):
        Tolerances(angle_deg=-1.0)


def _in_model_twin(seed: int, n: int, n_test: int = 300, **kw):
    """A twin whose geometric errors are all in the fitted parameter set (the truth a posterior can cover)."""
    twin = Twin.create(TwinConfig(seed=seed, **kw))
    active = twin.model.default_active()
    nominal = twin.model.nominal_vector()
    table = twin.model.layout.table_slice
    twin.x_true[table] = torch.where(active[table], twin.x_true[table], nominal[table])
    gen = torch.Generator().manual_seed(seed + 7919)
    return twin, twin.sample(n, gen), twin.sample(n_test, gen)


def _z_scores(result, twin) -> np.ndarray:
    layout = result.model.layout
    rows = prior_table(list(layout.names), layout.is_angle().tolist(), result.prior, result.x, result.covariance)
    scale = layout.unit_scale()
    z = []
    for row in rows:
        i = layout.index(row["name"])
        z.append(abs(row["posterior"] - float(twin.x_true[i] * scale[i])) / row["posterior_sigma"])
    return np.array(z)


def test_twin_parameters_fall_inside_their_posterior_sigmas_at_the_claimed_rate():
    z = np.concatenate([_z_scores(calibrate(t.robot, train, prior=PriorSpec()), t)
                        for t, train, _ in (_in_model_twin(seed, 120) for seed in range(4))])
    # Gaussian rates 68.3 / 95.4 / 99.7 %; 4 x 28 parameters, not all independent
    assert 0.55 < np.mean(z < 1) < 0.85
    assert np.mean(z < 2) > 0.88
    assert np.mean(z < 3) > 0.96


def test_few_poses_are_calibrated_where_the_rank_cut_refuses():
    twin, train, test = _in_model_twin(3, 10)
    with pytest.raises(DataError, match="no more than the"):
        calibrate(twin.robot, train)
    result = calibrate(twin.robot, train, prior=PriorSpec())
    nominal = calibrate(twin.robot, train, prior=PriorSpec(scale=0.0))

    def rms(r):
        return float((test.position - r.model.tcp_position(test.q, r.x)).norm(dim=1).pow(2).mean().sqrt())

    assert rms(result) < 0.7 * rms(nominal)
    assert np.mean(_z_scores(result, twin) < 3) > 0.9


def test_nominal_candidate_fits_only_frame_and_tool(robot):
    _, train, _ = _in_model_twin(2, 40)
    result = calibrate(robot, train, prior=PriorSpec(scale=0.0))
    names = result.free_names
    assert all(n.startswith(("base_", "tool_")) for n in names)
    table = result.model.layout.table_slice
    assert torch.equal(result.x[table], result.model.nominal_vector()[table])


def test_orientation_only_parameter_stays_at_prior_with_a_wrong_tool_rotation():
    """Position data with the reflector on the last axis say nothing of theta6 (it only turns the tool)."""
    twin = Twin.create(TwinConfig(seed=5, tool_error_mm=0.0))
    layout = twin.model.layout
    tool = twin.x_true[layout.tool_slice]
    tool[:2] = 0.0  # reflector on axis 6
    tool[3:] = torch.tensor([0.1, -0.2, 0.15], dtype=torch.float64)  # a tool rotation of ~15 deg nobody measured
    twin.x_true[layout.index("theta6")] += math.radians(3.0)  # and a joint-6 offset far beyond tolerance
    gen = torch.Generator().manual_seed(5)
    train = twin.sample(100, gen)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = calibrate(twin.robot, train, prior=PriorSpec())
    rows = {r["name"]: r for r in prior_table(list(layout.names), layout.is_angle().tolist(), result.prior, result.x,
                                              result.covariance)}
    assert abs(rows["theta6"]["moved_sigmas"]) < 1e-3 and rows["theta6"]["sigma_ratio"] > 0.99
    assert "tool_rx" not in rows  # not estimated without orientation data
    for name in ("alpha6", "a6"):
        assert abs(rows[name]["moved_sigmas"]) < 2.0, rows[name]


def test_log_evidence_of_a_linear_model_is_the_exact_gaussian_marginal_likelihood():
    """Linear model, Gaussian prior: log N(y; A mu, s^2 I + A Sigma A^T), whatever the MAP's route."""
    from scipy.stats import multivariate_normal

    from torchcal.identify.prior import log_evidence

    gen = torch.Generator().manual_seed(5)
    a = torch.randn(25, 3, generator=gen, dtype=torch.float64)
    y = torch.randn(25, generator=gen, dtype=torch.float64)
    mean = torch.tensor([0.2, -0.1, 0.5], dtype=torch.float64)
    sigma = torch.tensor([0.3, 2.0, 0.05], dtype=torch.float64)
    prior = _prior(3, mean, sigma)
    s = 0.4
    h = a.T @ a / s**2 + prior.precision
    x = torch.linalg.solve(h, a.T @ y / s**2 + prior.precision @ mean)
    problem = LinearProblem(a, y, torch.arange(3))
    r, jac = problem.jacobian(x)
    value = log_evidence(jac, r, prior.precision, x - mean, s)
    cov = s**2 * torch.eye(25, dtype=torch.float64) + a @ torch.diag(sigma**2) @ a.T
    exact = multivariate_normal(mean=(a @ mean).numpy(), cov=cov.numpy()).logpdf(y.numpy())
    assert abs(value - exact) < 1e-8


def test_extended_prior_without_extra_entries_is_the_prior_itself():
    """Every joint-space coefficient dropped (extra 0): the mean keeps its length (it once went negative)."""
    prior = _prior(3, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), torch.ones(3, dtype=torch.float64))
    same = prior.extended(torch.arange(3), 0, 5)
    assert same.mean.tolist() == [1.0, 2.0, 3.0, 0.0, 0.0] and torch.equal(same.precision, prior.precision)
    two = prior.extended(torch.tensor([0, 1, 2, 4]), 1, 5)
    assert two.precision.shape == (4, 4) and float(two.precision[3, 3]) == 0.0 and math.isinf(float(two.sigma[3]))
    with pytest.raises(ModelError):
        prior.extended(torch.tensor([0, 1, 2, 5]), 1, 5)


def test_evidence_prefers_calibrating_a_robot_with_errors_and_not_one_without():
    """A twin built with tolerance-sized errors: the nominal robot is far less probable. The same poses
    measured on the nominal robot itself: no scale beats the nominal candidate by more than the tie."""
    from torchcal.model_selection.prior_scale import EVIDENCE_TIE, evidence_prior_scales

    twin, train, _ = _in_model_twin(1, 80)

    def fitter(spec):
        return lambda data, start=None: calibrate(twin.robot, data, prior=spec, start=start)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        chosen, record, full = evidence_prior_scales(fitter, PriorSpec(), train)
        assert not chosen.nominal and full.prior.spec.scale == chosen.scale
        deltas = {c["name"]: c["delta_log_evidence"] for c in record["candidates"]}
        assert deltas["nominal"] < -10 * EVIDENCE_TIE
        exact = twin.model.tcp_position(train.q, twin.model.nominal_vector())
        clean = replace(train, position=exact + 2e-5 * torch.randn(exact.shape, generator=torch.Generator().manual_seed(3),
                                                                    dtype=torch.float64))
        chosen, record, _ = evidence_prior_scales(fitter, PriorSpec(), clean)
    assert chosen.nominal or chosen.scale == 0.25, record["table"]


def test_a_warm_started_fit_reaches_the_cold_fit_in_fewer_steps():
    """The fold fits start from the fit on all poses: same minimum (the fold's own), fewer iterations."""
    twin, train, _ = _in_model_twin(2, 120)
    fold = train.subset(np.arange(0, 120, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        full = calibrate(twin.robot, train, prior=PriorSpec())
        cold = calibrate(twin.robot, fold, prior=PriorSpec())
        warm = calibrate(twin.robot, fold, prior=PriorSpec(), start=full)
    p_cold = cold.model.tcp_position(train.q, cold.x)
    p_warm = warm.model.tcp_position(train.q, warm.x)
    assert float((p_cold - p_warm).norm(dim=-1).max()) < 1e-6  # m: the same model, predicted on every pose
    sd = cold.covariance.diagonal().sqrt()
    assert float(((cold.x[cold.free] - warm.x[warm.free]).abs() / sd).max()) < 0.1
    assert warm.solve.iterations <= cold.solve.iterations
