"""Multilateration on simulated tracer sessions, checked against the known true geometry."""

from __future__ import annotations

import math

import pytest
import torch

from torchcal.core.errors import DataError, TorchcalError
from torchcal.instruments.tracer.lengths import (
    LengthSigma,
    points_from_stations,
    station_distances,
    stations_from_points,
    tracer_lengths,
)
from torchcal.instruments.tracer.multilateration import (
    _covariance_station_gauge,
    _free_mask,
    _inner_constraint_transform,
    _normal_equations,
    _Problem,
    _residuals,
    _station_frame,
    multilaterate,
    predict_covariance,
)
from torchcal.instruments.tracer.plan import plan_tracer_setup
from torchcal.instruments.tracer.twin import simulate_tracer_lengths

SIGMA = LengthSigma()


def _session(seed: int = 7, n_points: int = 60, n_stations: int = 4, visibility=None):
    g = torch.Generator().manual_seed(seed)
    plan = plan_tracer_setup(torch.tensor([0.9, 0.1, 0.6]), 0.3, n_points, n_stations, g, SIGMA)
    # interferometers zeroed near the first point: dead path = that distance plus a few mm
    dead = station_distances(plan.points[:1], plan.stations)[0] + 0.005 * torch.randn(n_stations, generator=g, dtype=torch.float64)
    lengths = simulate_tracer_lengths(plan.points, plan.stations, dead, SIGMA, g, visibility)
    return plan, dead, lengths


def _align(source: torch.Tensor, target: torch.Tensor):
    """Orthogonal (mirror allowed: lengths cannot see it) fit ``target ~ R source + t``."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    u, _, vt = torch.linalg.svd((target - mu_t).T @ (source - mu_s))
    rot = u @ vt
    return rot, mu_t - rot @ mu_s


def _errors_in_result_frame(result, points, stations):
    """Truth moved onto the result by the points-only fit (the inner constraint of the points gauge)."""
    rot, t = _align(points, result.points)
    return result.points - (points @ rot.T + t), result.stations - (stations @ rot.T + t)


def test_twin_lengths_follow_the_model_and_noise():
    g = torch.Generator().manual_seed(0)
    points = torch.rand(4000, 3, generator=g, dtype=torch.float64)
    stations = torch.tensor([[2.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, 0.0, 2.5], [-2.0, -1.0, 0.5]], dtype=torch.float64)
    dead = torch.tensor([0.1, -0.2, 1.0, 0.0], dtype=torch.float64)
    lengths = simulate_tracer_lengths(points, stations, dead, SIGMA, g, visibility=0.25)
    exact = (points.unsqueeze(1) - stations).norm(dim=-1) - dead
    seen = torch.isfinite(lengths)
    assert abs(seen.double().mean().item() - 0.75) < 0.02
    z = (lengths - exact)[seen] / SIGMA((points.unsqueeze(1) - stations).norm(dim=-1))[seen]
    assert abs(z.mean().item()) < 0.05 and abs(z.std().item() - 1.0) < 0.05


def test_jacobian_matches_finite_differences():
    g = torch.Generator().manual_seed(3)
    p = torch.randn(7, 3, generator=g, dtype=torch.float64)
    q = torch.cat([3 * torch.randn(4, 3, generator=g, dtype=torch.float64), torch.rand(4, 1, generator=g, dtype=torch.float64)], -1)
    lengths = tracer_lengths(p, q[:, :3], q[:, 3]) + 1e-3 * torch.randn(7, 4, generator=g, dtype=torch.float64)
    mask = torch.ones(7, 4, dtype=torch.float64)
    mask[2, 1] = 0.0
    problem = _Problem(lengths * mask, mask, mask / 1e-3)
    _, a, b, *_ = _normal_equations(problem, p, q)
    h = 1e-7
    for i, k in [(0, 0), (2, 1), (6, 2)]:
        dp = torch.zeros_like(p)
        dp[i, k] = h
        fd = (_residuals(problem, p + dp, q) - _residuals(problem, p - dp, q)) / (2 * h)
        torch.testing.assert_close(fd[i], a[i, :, k], rtol=1e-6, atol=1e-6)
    for j, k in [(0, 0), (1, 2), (3, 3)]:
        dq = torch.zeros_like(q)
        dq[j, k] = h
        fd = (_residuals(problem, p, q + dq) - _residuals(problem, p, q - dq)) / (2 * h)
        torch.testing.assert_close(fd[:, j], b[:, j, k], rtol=1e-6, atol=1e-6)


def test_closed_form_stations_from_exact_points():
    plan, dead, _ = _session()
    exact = tracer_lengths(plan.points, plan.stations, dead)
    s, d = stations_from_points(plan.points, exact)
    torch.testing.assert_close(s, plan.stations, atol=1e-9, rtol=0)
    torch.testing.assert_close(d, dead, atol=1e-9, rtol=0)
    torch.testing.assert_close(points_from_stations(plan.stations, dead, exact), plan.points, atol=1e-9, rtol=0)


def test_recovers_geometry_within_predicted_uncertainty():
    plan, dead, lengths = _session()
    result = multilaterate(lengths, sigma=SIGMA)
    assert result.converged and result.dof == 240 - (180 + 16 - 6)
    assert 0.5 < result.variance_factor < 1.6
    dp, ds = _errors_in_result_frame(result, plan.points, plan.stations)
    rms = dp.pow(2).sum(-1).mean().sqrt().item()
    predicted = result.point_rms_sigma
    assert 0.5 * predicted < rms < 1.3 * predicted, (rms, predicted)
    assert (ds.abs() <= 3 * result.station_sigmas + 1e-12).all()
    assert ((result.dead_paths - dead).abs() <= 3 * result.dead_path_sigmas).all()
    # per-point weights are the inverse blocks of the reported covariance
    eye = torch.eye(3, dtype=torch.float64).expand(60, 3, 3)
    torch.testing.assert_close(result.point_weights @ result.point_covariances, eye, atol=1e-6, rtol=0)


def test_points_gauge_has_no_rigid_motion_and_is_datum_independent():
    plan, _, lengths = _session()
    result = multilaterate(lengths, sigma=SIGMA)
    n = result.n_points
    cov_p = result.covariance[: 3 * n]
    # inner constraints: the points' mean displacement and mean rotation have zero variance
    assert cov_p.reshape(n, 3, -1).sum(0).abs().max() < 1e-9 * result.covariance.diagonal().max()
    stations_gauge = multilaterate(lengths, sigma=SIGMA, gauge="stations")
    a, b, c = stations_gauge.datum_stations
    s = stations_gauge.station_sigmas
    assert float(s[a].abs().max()) == 0.0 and float(s[b, 1:].abs().max()) == 0.0 and float(s[c, 2]) == 0.0
    # two different station datums: different covariances, the same points-gauge covariance
    covs = []
    for abc in [(0, 1, 2), (1, 3, 2)]:
        p, st = _station_frame(plan.points, plan.stations, abc)
        dist = (p.unsqueeze(1) - st).norm(dim=-1)
        ones = torch.ones_like(dist)
        problem = _Problem(dist, ones, 1.0 / SIGMA(dist))
        q = torch.cat([st, torch.zeros(4, 1, dtype=torch.float64)], -1)
        cov, _, _ = _covariance_station_gauge(problem, p, q, _free_mask(4, abc, "cpu"))
        rot, _ = _align(p, plan.points)  # back to one common frame
        blocks = torch.block_diag(*([rot] * 64), torch.eye(4, dtype=torch.float64))
        tr = _inner_constraint_transform(p, st)
        covs.append((blocks @ cov @ blocks.T, blocks @ tr @ cov @ tr.T @ blocks.T))
    assert (covs[0][0] - covs[1][0]).abs().max() > 0.1 * covs[0][0].diagonal().max()
    torch.testing.assert_close(covs[1][1], covs[0][1], rtol=0, atol=1e-9 * float(covs[0][1].diagonal().max()))
    predicted, _ = predict_covariance(plan.points, plan.stations, SIGMA)
    torch.testing.assert_close(predicted, covs[0][1], rtol=0, atol=1e-9 * float(covs[0][1].diagonal().max()))


def test_missing_lengths():
    g = torch.Generator().manual_seed(2)
    visible = torch.ones(60, 4, dtype=torch.bool)
    rows = torch.randperm(60, generator=g)[:20]  # a third of the poses lose one beam each
    visible[rows, torch.randint(0, 4, (20,), generator=g)] = False
    plan, dead, lengths = _session(seed=11, visibility=visible)
    missing = ~torch.isfinite(lengths)
    assert missing.sum() > 5
    result = multilaterate(lengths, sigma=SIGMA)
    assert torch.isnan(result.residuals[missing]).all() and torch.isfinite(result.residuals[~missing]).all()
    dp, _ = _errors_in_result_frame(result, plan.points, plan.stations)
    assert dp.pow(2).sum(-1).mean().sqrt().item() < 1.3 * result.point_rms_sigma
    assert ((result.dead_paths - dead).abs() <= 3 * result.dead_path_sigmas).all()


def test_reference_points_and_initial_guess_give_the_same_solution():
    plan, _, lengths = _session()
    g = torch.Generator().manual_seed(5)
    nominal = plan.points + 2e-3 * torch.randn(60, 3, generator=g, dtype=torch.float64)
    free = multilaterate(lengths, sigma=SIGMA, reference_points=nominal)
    guided = multilaterate(lengths, sigma=SIGMA, initial=nominal, reference_points=nominal)
    torch.testing.assert_close(guided.points, free.points, atol=1e-9, rtol=0)
    torch.testing.assert_close(guided.dead_paths, free.dead_paths, atol=1e-9, rtol=0)
    # in the reference frame the points land on the truth up to the reference's own noise
    assert (free.points - plan.points).norm(dim=-1).mean() < 1e-3


def test_a_posteriori_covariance_without_sigma():
    _, _, lengths = _session()
    prior = multilaterate(lengths, sigma=SIGMA)
    post = multilaterate(lengths)
    assert post.covariance_scaled and not prior.covariance_scaled
    torch.testing.assert_close(post.covariance, prior.covariance * prior.variance_factor, rtol=1e-6, atol=1e-24)


def test_gross_error_with_four_stations_names_the_point_and_rejects_it():
    plan, dead, lengths = _session()
    bad = lengths.clone()
    bad[17, 2] += 0.5e-3
    # one redundant length per point: the point is found, the station cannot be
    with pytest.raises(DataError, match=r"point 17: one of its lengths l1, l2, l3, l4") as info:
        multilaterate(bad, sigma=SIGMA)
    assert info.value.row == 17
    result = multilaterate(bad, sigma=SIGMA, outliers="reject")
    assert result.rejected.tolist() == [[17, 0], [17, 1], [17, 2], [17, 3]]
    assert torch.isnan(result.points[17]).all() and torch.isnan(result.residuals[17]).all()
    keep = torch.arange(60) != 17
    assert torch.isfinite(result.points[keep]).all()
    rot, t = _align(plan.points[keep], result.points[keep])
    dp = result.points[keep] - (plan.points[keep] @ rot.T + t)
    assert dp.pow(2).sum(-1).mean().sqrt().item() < 1.3 * result.point_rms_sigma * math.sqrt(60 / 59)
    assert ((result.dead_paths - dead).abs() <= 3 * result.dead_path_sigmas).all()


def test_gross_error_with_six_stations_names_point_and_station():
    plan, _dead, lengths = _session(seed=4, n_points=30, n_stations=6)
    bad = lengths.clone()
    bad[11, 4] -= 0.3e-3
    with pytest.raises(DataError, match=r"point 11, station 5 \(column 'l5'\)") as info:
        multilaterate(bad, sigma=SIGMA)
    assert info.value.row == 11 and info.value.column == "l5"
    result = multilaterate(bad, sigma=SIGMA, outliers="reject")
    assert result.rejected.tolist() == [[11, 4]]
    assert math.isnan(float(result.residuals[11, 4])) and torch.isfinite(result.points).all()
    dp, _ = _errors_in_result_frame(result, plan.points, plan.stations)
    assert dp.pow(2).sum(-1).mean().sqrt().item() < 1.3 * result.point_rms_sigma


def test_inconsistent_lengths_are_reported():
    _, _, lengths = _session()
    bad = lengths.clone()
    bad[:, 1] = bad[:, 1] * 1.02  # a station with a wrong scale: fits no geometry
    with pytest.raises(TorchcalError, match=r"station|geometry|gross"):
        multilaterate(bad, sigma=SIGMA)


@pytest.mark.parametrize(
    ("edit", "pattern"),
    [
        (lambda l: l[:, :3], "at least 4 stations"),
        (lambda l: l[:9], "cannot determine"),
        (lambda l: _drop(l, (slice(4, None), 1)), r"station 2 \(column 'l2'\) saw only 4"),
        (lambda l: _drop(l, (5, slice(0, 2))), "point 5 was seen by only 2"),
        (lambda l: _drop(l, (slice(0, 55), 0)), "a point seen by only 3 stations adds no redundancy"),
    ],
)
def test_unidentifiable_inputs_raise_clear_errors(edit, pattern):
    _, _, lengths = _session()
    with pytest.raises(DataError, match=pattern):
        multilaterate(edit(lengths.clone()), sigma=SIGMA)


def test_start_needs_complete_rows_unless_given_points():
    plan, dead, lengths = _session(seed=4, n_points=30, n_stations=6)
    lengths[:15, 0] = torch.nan  # no pose is seen by every station
    lengths[15:, 1] = torch.nan
    with pytest.raises(DataError, match="seen by every station"):
        multilaterate(lengths, sigma=SIGMA)
    result = multilaterate(lengths, sigma=SIGMA, initial=plan.points + 1e-3)
    assert ((result.dead_paths - dead).abs() <= 3 * result.dead_path_sigmas).all()


def _drop(lengths: torch.Tensor, index) -> torch.Tensor:
    lengths[index] = torch.nan
    return lengths


def test_planner_prediction_matches_monte_carlo():
    g = torch.Generator().manual_seed(21)
    plan = plan_tracer_setup(torch.tensor([0.0, 0.7, 0.5]), 0.25, 40, 4, g, SIGMA)
    dead = station_distances(plan.points[:1], plan.stations)[0]
    point_sq, dead_z2, reps = [], [], 10
    for _ in range(reps):
        lengths = simulate_tracer_lengths(plan.points, plan.stations, dead, SIGMA, g)
        result = multilaterate(lengths, sigma=SIGMA, initial=plan.points, reference_points=plan.points)
        dp = result.points - plan.points  # the reference fit is the points gauge's datum
        point_sq.append(dp.pow(2).sum(-1).mean())
        dead_z2.append(((result.dead_paths - dead) / plan.dead_path_sigmas) ** 2)
    ratio = math.sqrt(float(torch.stack(point_sq).mean())) / plan.point_rms_sigma
    assert 0.85 < ratio < 1.15, ratio
    assert 0.4 < float(torch.cat(dead_z2).mean()) < 1.8
