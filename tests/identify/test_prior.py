"""MAP identification with a prior: closed forms, unseen directions, coverage on twins, overrides."""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass, replace

import numpy as np
import pytest
import torch

from torchcal.core.errors import DataError, ModelError
from torchcal.identify.calibrate import calibrate
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.identify.prior import (
    EarlierModel,
    PriorProblem,
    PriorSpec,
    Tolerances,
    beyond_tolerance_warning,
    parameter_kind,
    posterior_covariance,
    prior_table,
    resolve_tolerances,
    solve_map,
    taught_summary,
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


def _map_covariances(a: torch.Tensor, units: np.ndarray, noise: float, shared: float, reps: int):
    """Monte-Carlo of the near-flat-prior MAP of ``y = offset[region] + noise`` (2 rows per pose).

    Returns the averaged classical and widened posterior covariances and the empirical covariance of the
    estimate over the repetitions. ``s`` is the data's own, ``|r|^2 / (m - 2)``, as the fit re-estimates it.
    """
    m, rows_per_pose = len(units), 2
    pose_units = units[::rows_per_pose]
    assert np.array_equal(np.repeat(pose_units, rows_per_pose), units)  # a pose's rows share its region
    lam = 1e-6 * torch.eye(2, dtype=torch.float64)  # sigma 1000 against posterior sigmas ~1e-3: near flat
    gen = torch.Generator().manual_seed(2)
    classical = torch.zeros(2, 2, dtype=torch.float64)
    widened = torch.zeros(2, 2, dtype=torch.float64)
    estimates = []
    for _ in range(reps):
        y = shared * torch.randn(int(units.max()) + 1, generator=gen, dtype=torch.float64)[units] + \
            noise * torch.randn(m, generator=gen, dtype=torch.float64)
        ls = torch.linalg.solve(a.T @ a, a.T @ y)
        s = float((y - a @ ls).norm()) / (m - 2) ** 0.5
        x = torch.linalg.solve(a.T @ a / s**2 + lam, a.T @ y / s**2)  # the MAP, closed form
        r = y - a @ x
        classical += posterior_covariance(-a, r, lam, s)[0]
        widened += posterior_covariance(-a, r, lam, s, pose_units, rows_per_pose)[0]
        estimates.append(x)
    return classical / reps, widened / reps, torch.cov(torch.stack(estimates).T)


def test_posterior_covariance_widens_to_the_sampling_covariance_of_residuals_shared_within_regions():
    """A straight line over 40 regions whose residuals share one offset per region: the classical
    ``(J^T J / s^2 + Lambda)^-1`` misses the shared part; widened to the cluster-robust estimate it matches the
    Monte-Carlo covariance of the estimate. Without a shared offset it stays near the classical one."""
    from tests.identify.test_uncertainty import _design, _true_covariance

    a, units = _design(40, 10)
    classical, widened, empirical = _map_covariances(a, units, noise=0.01, shared=0.02, reps=400)
    # the Monte Carlo is the truth here; it agrees with the closed form of a shared offset
    assert torch.allclose(empirical.diagonal(), _true_covariance(a, units, 0.01, 0.02).diagonal(), rtol=0.2)
    assert (classical.diagonal() < 0.3 * empirical.diagonal()).all(), (classical, empirical)
    assert torch.allclose(widened.diagonal(), empirical.diagonal(), rtol=0.2), (widened, empirical)
    classical, widened, _ = _map_covariances(a, units, noise=0.01, shared=0.0, reps=150)
    assert torch.allclose(classical.diagonal(), _true_covariance(a, units, 0.01, 0.0).diagonal(), rtol=0.1)
    # the max of two estimates can only add; with nothing shared it adds little
    assert (widened.diagonal() >= classical.diagonal() * (1 - 1e-12)).all()
    assert torch.allclose(widened.diagonal(), classical.diagonal(), rtol=0.2), (widened, classical)


def _layout(robot):
    from torchcal.kinematics.error_model import ErrorModel

    model = ErrorModel(robot)
    return list(model.layout.names), torch.nonzero(model.default_active()).squeeze(-1), model.nominal_vector()


def test_an_earlier_model_gives_the_prior_mean_and_the_inverse_of_its_covariance_block(robot):
    """``PriorSpec(earlier=...)``: the earlier estimate as mean and the inverse of its (scaled) covariance as
    precision over the robot parameters it estimated; the instrument frame keeps no prior; parameters it did
    not estimate keep their tolerance."""
    names, free, nominal = _layout(robot)
    mdh = ["alpha2", "a2", "theta2", "d4", "theta6"]
    # instrument-frame entries among them; the tool's earlier block: test_an_earlier_tool_block_is_never_scaled
    taken = [mdh[0], "base_x", *mdh[1:3], "base_rz", *mdh[3:]]
    gen = torch.Generator().manual_seed(0)
    root = torch.randn(len(taken), len(taken), generator=gen, dtype=torch.float64) * 1e-4
    cov = root @ root.T + 1e-10 * torch.eye(len(taken), dtype=torch.float64)  # correlated, frame included
    x = nominal + 1e-3 * torch.randn(len(nominal), generator=gen, dtype=torch.float64)
    earlier = EarlierModel(x=x, indices=torch.tensor([names.index(n) for n in taken]), covariance=cov, label="earlier")
    scale = 2.0
    prior = PriorSpec(scale=scale, earlier=earlier).build(names, free, nominal)
    pos = {names[i]: k for k, i in enumerate(free.tolist())}
    for n in names:
        expected = x[names.index(n)] if n in mdh else nominal[names.index(n)]
        assert float(prior.mean[names.index(n)]) == float(expected), n
    # the earlier covariance over the MDH entries (the frame marginalised out), sigmas times the scale
    sub = [taken.index(n) for n in mdh]
    block = cov.numpy()[np.ix_(sub, sub)] * scale**2
    rows = [pos[n] for n in mdh]
    got = prior.precision.numpy()[np.ix_(rows, rows)]
    np.testing.assert_allclose(got, np.linalg.inv(block), rtol=1e-6)
    np.testing.assert_allclose(prior.sigma[rows].numpy(), np.sqrt(np.diag(block)), rtol=1e-6)
    others = [k for k in range(len(free)) if k not in rows]
    assert float(prior.precision[rows][:, others].abs().max()) == 0.0
    tol = Tolerances()
    for n, k in pos.items():
        if n.startswith("base_"):
            assert float(prior.precision[k].abs().max()) == 0.0 and math.isinf(float(prior.sigma[k])), n
        elif n not in mdh:
            expected = {"length_mm": tol.length_mm * 1e-3 * scale, "angle_deg": math.radians(tol.angle_deg) * scale,
                        "joint_offset_deg": math.radians(tol.joint_offset_deg) * scale,
                        "tool_mm": tol.tool_mm * 1e-3}[parameter_kind(n)]
            assert float(prior.sigma[k]) == pytest.approx(expected, rel=1e-12), n
            assert float(prior.precision[k, k]) == pytest.approx(expected**-2, rel=1e-9), n


@pytest.mark.parametrize("scale", [0.0, 1.0, 4.0])
def test_an_earlier_tool_block_is_never_scaled(robot, scale):
    """The tool is the user's: its earlier covariance is its prior at every scale, the nominal candidate (0)
    included (it was scaled to zero there: a tool with no prior reported with sigma 0); the table's block
    scales; an entry without a prior keeps sigma inf (not inf * 0)."""
    names, free, nominal = _layout(robot)
    taken = ["a2", "d4", "tool_x", "tool_y", "tool_z"]
    gen = torch.Generator().manual_seed(3)
    root = torch.randn(5, 5, generator=gen, dtype=torch.float64) * 1e-4
    cov = root @ root.T + 1e-10 * torch.eye(5, dtype=torch.float64)
    earlier = EarlierModel(x=nominal.clone(), indices=torch.tensor([names.index(n) for n in taken]), covariance=cov,
                           label="earlier")
    if scale == 0.0:  # the nominal candidate: the table is fixed, not free (calibrate drops it)
        free = torch.tensor([i for i in free.tolist() if names[i].startswith(("tool_", "base_"))])
    prior = PriorSpec(scale=scale, earlier=earlier).build(names, free, nominal)
    pos = {names[i]: k for k, i in enumerate(free.tolist())}
    factor = np.array([scale, scale, 1.0, 1.0, 1.0])
    block = factor[:, None] * cov.numpy() * factor[None, :]
    kept = [k for k, n in enumerate(taken) if n in pos]
    rows = [pos[taken[k]] for k in kept]
    expected = np.linalg.pinv(block[np.ix_(kept, kept)])
    np.testing.assert_allclose(prior.precision.numpy()[np.ix_(rows, rows)], expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())
    tool = [pos[n] for n in ("tool_x", "tool_y", "tool_z")]
    marginal = np.sqrt(np.diag(np.linalg.pinv(prior.precision.numpy())[np.ix_(tool, tool)]))
    np.testing.assert_allclose(prior.sigma[tool].numpy(), marginal, rtol=1e-6)
    assert (prior.sigma[tool] > 0).all() and torch.isfinite(prior.sigma[tool]).all()
    for n, k in pos.items():
        if n.startswith("base_"):
            assert math.isinf(float(prior.sigma[k])) and float(prior.precision[k].abs().max()) == 0.0, n


def test_a_recalibration_on_few_poses_with_an_earlier_model_as_prior_lands_nearer_the_truth():
    """A fit on 150 poses, then 12 new poses of the same robot: with the first fit as prior the model predicts the
    twin's true positions better than the same 12 poses with the tolerance prior."""
    twin, train, _ = _in_model_twin(2, 150)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        first = calibrate(twin.robot, train, prior=PriorSpec())
        earlier = EarlierModel(x=first.x, indices=first.free, covariance=first.covariance, label="first")
        gen = torch.Generator().manual_seed(102)
        few, check = twin.sample(12, gen), twin.sample(400, gen)
        with_earlier = calibrate(twin.robot, few, prior=PriorSpec(earlier=earlier))
        tolerance = calibrate(twin.robot, few, prior=PriorSpec())
    truth = twin.true_positions(check.q)

    def rms(r):  # m, against the noise-free truth
        return float((truth - r.model.tcp_position(check.q, r.x)).norm(dim=1).pow(2).mean().sqrt())

    assert rms(with_earlier) < 0.6 * rms(tolerance), (rms(with_earlier), rms(tolerance), rms(first))
    assert rms(with_earlier) < 2.0 * rms(first)


def test_the_scale_multiplies_the_mdh_sigmas_and_not_the_tool(robot):
    """docs/prior.md: x4 gives 4 x 0.5 mm on lengths, 4 x 0.1 deg on joint offsets, 4 x 0.05 deg on angles; the
    tool keeps its 10 mm; the instrument frame has no prior."""
    names, free, nominal = _layout(robot)
    prior = PriorSpec(scale=4.0).build(names, free, nominal)
    pos = {names[i]: k for k, i in enumerate(free.tolist())}
    expected = {"a2": 4 * 0.5e-3, "d4": 4 * 0.5e-3, "theta3": math.radians(4 * 0.1), "theta6": math.radians(4 * 0.1),
                "alpha5": math.radians(4 * 0.05), "beta3": math.radians(4 * 0.05),
                "tool_x": 10e-3, "tool_y": 10e-3, "tool_z": 10e-3}
    for n, value in expected.items():
        k = pos[n]
        assert float(prior.sigma[k]) == pytest.approx(value, rel=1e-12), n
        assert float(prior.precision[k, k]) == pytest.approx(value**-2, rel=1e-9), n
    assert float(prior.tolerance_sigma[pos["a2"]]) == pytest.approx(0.5e-3)  # the tolerance band stays unscaled
    base = [n for n in pos if n.startswith("base_")]
    assert len(base) == 6
    for n in base:
        assert float(prior.precision[pos[n]].abs().max()) == 0.0 and math.isinf(float(prior.sigma[pos[n]])), n


@pytest.fixture(scope="module")
def alpha4_off_fit():
    """A position-only fit (200 poses) of a twin whose alpha4 is 0.6 deg (12 prior sigmas) below nominal, every
    other error within the fitted set and tolerance-sized (sigma 0.3 mm / 0.03 deg against 0.5 mm / 0.05 deg)."""
    twin, _, _ = _in_model_twin(0, 1, n_test=1)
    twin.x_true[twin.model.layout.index("alpha4")] -= math.radians(0.6)
    train = twin.sample(200, torch.Generator().manual_seed(11))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = calibrate(twin.robot, train, prior=PriorSpec())
    layout = result.model.layout
    rows = prior_table(list(layout.names), layout.is_angle().tolist(), result.prior, result.x, result.covariance)
    return twin, result, rows


def test_the_summary_counts_the_parameters_the_data_sharpened_and_names_those_at_their_prior(alpha4_off_fit):
    """theta6 only turns the tool (about axis 6, as tool_x/tool_y do): position data leave it at its prior.
    N of M: the count of posterior / prior sigma < 0.9, from the covariance and the prior directly."""
    _, result, rows = alpha4_off_fit
    names = result.model.layout.names
    post = result.covariance.diagonal().sqrt()
    ratio = {names[i]: float(post[k] / result.prior.sigma[k]) for k, i in enumerate(result.free.tolist())
             if math.isfinite(float(result.prior.sigma[k]))}
    assert len(ratio) == 27  # 24 MDH entries of twin-kr6 and the tool point; the instrument frame has no prior
    assert ratio["theta6"] > 0.99
    summary = taught_summary(rows)
    match = re.fullmatch(r"prior vs posterior: the data sharpened (\d+) of (\d+) parameters \(posterior sigma < 0\.9 "
                         r"prior\); (\d+) stay at their prior \(the data do not see them\): (.*)", summary)
    assert match, summary
    sharpened, total, stay = (int(match.group(i)) for i in (1, 2, 3))
    at_prior = match.group(4).split(", ")
    assert sharpened == sum(r < 0.9 for r in ratio.values()) and total == len(ratio), (summary, ratio)
    assert "theta6" in at_prior and stay == len(at_prior) == total - sharpened
    assert at_prior == [n for n in names if n in ratio and ratio[n] > 0.9]
    assert 15 <= sharpened < total  # the data determine most of the table, not all of it


def test_a_parameter_off_by_12_prior_sigmas_and_only_it_is_named_beyond_tolerance(alpha4_off_fit):
    twin, _, rows = alpha4_off_fit
    flagged = [r["name"] for r in rows if r["beyond_tolerance"]]
    assert flagged == ["alpha4"], [(r["name"], r["moved_sigmas"]) for r in rows if abs(r["moved_sigmas"]) > 2]
    row = next(r for r in rows if r["name"] == "alpha4")
    truth = math.degrees(float(twin.x_true[twin.model.layout.index("alpha4")] - twin.model.nominal_vector()[
        twin.model.layout.index("alpha4")]))
    assert -0.65 < truth < -0.55  # the 0.6 deg plus the twin's own small error there
    assert abs(row["posterior"] - row["prior"] - truth) < 0.05  # deg: the fit found the offset
    warning = beyond_tolerance_warning(rows)
    assert warning is not None and warning.startswith("1 parameter(s) moved beyond their manufacturing tolerance: ")
    assert re.search(r"alpha4 -0\.5\d* deg \(tolerance 0\.15\)", warning), warning
    others = [r["name"] for r in rows if r["name"] != "alpha4"]
    assert not any(re.search(rf"\b{n} ", warning) for n in others), warning


def test_a_6d_probe_mounted_at_any_angle_is_found_without_a_tolerance_warning():
    # the probe's rotation on the flange has no prior by default (the UR10's T-Mac sits at -90 deg about z):
    # the orientations find it, and nothing is named beyond a tolerance it does not have
    from torchcal.data.measurements import Measurements
    from torchcal.kinematics import transforms as tf
    from torchcal.stages.prior_options import prior_warning

    twin = Twin.create(TwinConfig(seed=2, gravity=False, gear=False))
    gen = torch.Generator().manual_seed(2)
    q = twin.robot.sample_joints(80, gen)
    probe = tf.so3_exp(torch.tensor([0.0, 0.0, -math.pi / 2], dtype=torch.float64))
    flange = twin.T_instrument_base() @ twin.model.base_flange_pose(q, twin.x_true)
    data = Measurements(q=q, position=twin.measure(q, gen), rotation=flange[..., :3, :3] @ probe)
    assert math.isinf(Tolerances().tool_deg) and "rotation free" in Tolerances().describe()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        free = calibrate(twin.robot, data, prior=PriorSpec())
        tight = calibrate(twin.robot, data, prior=PriorSpec(tolerances=Tolerances(tool_deg=5.0)))
    found = tf.so3_exp(free.x[free.model.layout.tool_slice][3:])
    assert math.degrees(float(tf.rotation_angle(found.T @ probe))) < 0.05
    assert prior_warning(free) is None or "tool_r" not in prior_warning(free)
    # a user who states a 5 deg tolerance is told the probe sits beyond it
    assert "tool_rz" in (prior_warning(tight) or "")
