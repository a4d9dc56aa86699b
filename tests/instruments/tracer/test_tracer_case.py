"""The tracer twin case: lengths follow the model, poses in the sphere, a consistent held-out file."""

from __future__ import annotations

import json
import math

import torch

from torchcal.data.measurements import load_measurements
from torchcal.instruments.tracer.data import load_tracer_data
from torchcal.instruments.tracer.lengths import station_distances
from torchcal.instruments.tracer.twin_case import (
    TracerTwinConfig,
    simulate_tracer_case,
    true_base_points,
    write_tracer_case,
)
from torchcal.kinematics.robot import load_robot


def test_lengths_follow_the_model_and_the_noise():
    config = TracerTwinConfig(seed=2, n_train=400, n_test=10)
    case = simulate_tracer_case(config)
    center = torch.tensor(config.sphere_center_mm, dtype=torch.float64) * 1e-3
    assert ((case.points_train - center).norm(dim=-1) <= config.sphere_radius_mm * 1e-3 + 1e-12).all()
    torch.testing.assert_close(case.points_train, true_base_points(case.twin, case.q_train), atol=0, rtol=0)
    dist = station_distances(case.points_train, case.stations)
    # stations 2.5 radii from the centre, spread as a regular tetrahedron (angle arccos(-1/3))
    rel = case.stations - center
    torch.testing.assert_close(rel.norm(dim=-1), torch.full((4,), 1.0, dtype=torch.float64), atol=1e-12, rtol=0)
    cos = (rel @ rel.T)[~torch.eye(4, dtype=torch.bool)]
    torch.testing.assert_close(cos, torch.full_like(cos, -1.0 / 3.0), atol=1e-12, rtol=0)
    z = (case.lengths + case.dead_paths - dist) / config.sigma(dist)
    assert abs(float(z.mean())) < 0.1 and abs(float(z.std()) - 1.0) < 0.06
    assert float(case.lengths[0].abs().max()) < 5e-6  # interferometers zeroed at the first pose


def test_held_out_points_are_tracker_points_of_the_true_robot():
    config = TracerTwinConfig(seed=4, n_train=20, n_test=300, test_sigma_mm=0.002)
    case = simulate_tracer_case(config)
    t = case.twin.T_instrument_base()
    clean = case.test_true_base @ t[:3, :3].T + t[:3, 3]
    noise = case.test.position - clean
    assert abs(float(noise.std()) - 2e-6) < 0.2e-6
    assert float(t[:3, 3].norm()) > 1.0  # a tracker frame far from the base: --register is needed


def test_loss_probability_and_files(tmp_path):
    config = TracerTwinConfig(seed=6, n_train=50, n_test=20, n_stations=6, loss_probability=0.2)
    paths = write_tracer_case(tmp_path, config)
    robot = load_robot(paths["robot.yaml"])
    data = load_tracer_data(paths["lengths.csv"], robot)
    assert data.lengths.shape[1] == 6
    assert abs(float((~data.seen).double().mean()) - 0.2) < 0.06
    test = load_measurements(paths["test.csv"], robot)
    assert len(test) == 20
    truth = json.loads(paths["truth.json"].read_text())
    assert len(truth["stations_mm"]) == 6 and len(truth["dead_paths_mm"]) == 6
    assert math.isclose(truth["noise_floor_rms_mm"], math.sqrt(3) * 0.001)
    # the written lengths reproduce the true geometry (mm in the file, dead paths from truth.json)
    stations = torch.tensor(truth["stations_mm"], dtype=torch.float64) * 1e-3
    dead = torch.tensor(truth["dead_paths_mm"], dtype=torch.float64) * 1e-3
    case = simulate_tracer_case(config)
    dist = station_distances(case.points_train, stations)
    err = (data.lengths + dead - dist)[data.seen]
    assert float(err.abs().max()) < 6 * float(config.sigma(dist).max())
