"""The loading-rig twin: files, truth ranges, wrench limits, noise statistics."""

from __future__ import annotations

import json
import math

import pytest
import torch

from torchcal.instruments.stiffness.data import load_stiffness
from torchcal.instruments.stiffness.twin import (
    StiffnessTwin,
    StiffnessTwinConfig,
    stiffness_csv_text,
    write_stiffness_case,
)
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.stiffness.vjm import deflection


def test_case_files_are_contract_files(tmp_path):
    paths = write_stiffness_case(tmp_path, StiffnessTwinConfig(seed=4), n_train=12, n_test=5, plan="random")
    header = paths["stiffness_train.csv"].read_text().splitlines()[0]
    assert header == "q1,q2,q3,q4,q5,q6,fx,fy,fz,tx,ty,tz,dx,dy,dz,drx,dry,drz,x,y,z"
    assert len(load_stiffness(paths["stiffness_train.csv"], n_joints=6)) == 12
    assert len(load_stiffness(paths["stiffness_test.csv"], n_joints=6)) == 5
    truth = json.loads(paths["stiffness_truth.json"].read_text())
    twin = StiffnessTwin(StiffnessTwinConfig(seed=4))
    assert truth["joint_stiffness_nm_per_rad"]["k_j2_rz"] == float(twin.joint_stiffness[1])
    assert math.isclose(truth["deflection_noise_floor_rms_mm"], math.sqrt(6) * 0.012)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(paths[k].name for k in paths)  # no temp files


def test_truth_ranges_limits_and_wrench_magnitudes():
    cfg = StiffnessTwinConfig(seed=9, max_force_n=250.0, max_torque_nm=20.0)
    twin = StiffnessTwin(cfg)
    k = twin.joint_stiffness
    assert bool(((k[:3] >= 1e5) & (k[:3] <= 5e5)).all()) and bool(((k[3:] >= 1e4) & (k[3:] <= 5e4)).all())
    gen = torch.Generator().manual_seed(1)
    data = twin.sample(300, gen)
    assert bool(twin.robot.within_limits(data.q).all())
    f, m = data.wrench[:, :3].norm(dim=-1), data.wrench[:, 3:].norm(dim=-1)
    assert float(f.max()) <= 250.0 and float(f.min()) >= 0.2 * 250.0 - 1e-9
    assert float(m.max()) <= 20.0 and float(m.min()) >= 0.2 * 20.0 - 1e-9
    _, jac = geometric_jacobian(twin.model, data.q, twin.x_true)
    assert float(torch.linalg.svdvals(jac)[:, -1].min()) >= cfg.min_singular_value


def test_noise_matches_the_floor_and_loads_bend_as_the_vjm_says():
    twin = StiffnessTwin(StiffnessTwinConfig(seed=1))
    gen = torch.Generator().manual_seed(3)
    data = twin.sample(1500, gen)
    loaded, free = twin.loaded_pose(data.q, data.wrench), twin.unloaded_pose(data.q)
    true_def = loaded[:, :3, 3] - free[:, :3, 3]
    noise = (data.deflection - true_def).norm(dim=-1).pow(2).mean().sqrt() * 1e3
    assert abs(float(noise) / twin.noise_floor_mm() - 1) < 0.03
    # The first-order VJM law explains the simulated (exact-equilibrium) deflection to ~1 %.
    vjm = deflection(twin.model, data.q, twin.x_true, twin.compliance, data.wrench)[:, :3]
    rel = (vjm - true_def).norm(dim=-1).pow(2).mean().sqrt() / true_def.norm(dim=-1).pow(2).mean().sqrt()
    assert 0 < float(rel) < 0.02
    # Unloaded points are the true TCP in the (registered) instrument frame, plus noise.
    unloaded_err = (data.unloaded - free[:, :3, 3]).norm(dim=-1).pow(2).mean().sqrt()
    assert abs(float(unloaded_err) * 1e3 / (math.sqrt(3) * 0.012) - 1) < 0.05
    true_rot = tf.so3_log(loaded[:, :3, :3] @ free[:, :3, :3].transpose(-1, -2))
    rot_noise = (data.rotation - true_rot).norm(dim=-1).pow(2).mean().sqrt()
    assert abs(float(rot_noise) / (math.sqrt(6) * math.radians(0.01)) - 1) < 0.05


def test_without_unloaded_points_the_instrument_is_the_base():
    twin = StiffnessTwin(StiffnessTwinConfig(seed=1, with_unloaded=False, with_rotation=False))
    assert torch.equal(twin.T_instrument_base, torch.eye(4, dtype=torch.float64))
    data = twin.sample(4, torch.Generator().manual_seed(0))
    assert data.unloaded is None and data.rotation is None


def test_random_plan_writes_the_files_of_earlier_versions(tmp_path):
    """plan=random: one generator, random training sample then random test sample, truth as before."""
    cfg = StiffnessTwinConfig(seed=3)
    paths = write_stiffness_case(tmp_path, cfg, n_train=15, n_test=6, plan="random")
    twin = StiffnessTwin(cfg)
    gen = torch.Generator().manual_seed(3 + 104729)
    assert paths["stiffness_train.csv"].read_text() == stiffness_csv_text(twin.sample(15, gen))
    assert paths["stiffness_test.csv"].read_text() == stiffness_csv_text(twin.sample(6, gen))
    assert paths["stiffness_truth.json"].read_text() == json.dumps(twin.truth_dict(), indent=2) + "\n"


def test_optimal_plan_loads_at_the_rig_limits_and_reports_sigma(tmp_path):
    cfg = StiffnessTwinConfig(seed=5, max_force_n=200.0, max_torque_nm=25.0)
    paths = write_stiffness_case(tmp_path, cfg, n_train=20, n_test=8, plan_candidates=50)
    data = load_stiffness(paths["stiffness_train.csv"], n_joints=6)
    assert len(data) == 20
    assert torch.allclose(data.wrench[:, :3].norm(dim=-1), torch.full((20,), 200.0, dtype=torch.float64), rtol=1e-9)
    assert torch.allclose(data.wrench[:, 3:].norm(dim=-1), torch.full((20,), 25.0, dtype=torch.float64), rtol=1e-9)
    assert bool(StiffnessTwin(cfg).robot.within_limits(data.q).all())
    test = load_stiffness(paths["stiffness_test.csv"], n_joints=6)
    assert float(test.wrench[:, :3].norm(dim=-1).min()) < 200.0  # the test poses stay randomly loaded
    plan = json.loads(paths["stiffness_truth.json"].read_text())["loading_plan"]
    assert plan["plan"] == "optimal" and plan["candidate_poses"] == 50 and plan["n_poses"] == 20
    sigma = plan["predicted_relative_std_at_truth"]
    assert sorted(sigma) == [f"k_j{i}_rz" for i in range(1, 7)]
    assert all(0 < v < 1 for v in sigma.values())
    # the design point is the middle of the prior ranges, not the truth
    assert plan["design_stiffness"]["k_j6_rz"] == pytest.approx(math.sqrt(1e4 * 5e4), rel=1e-12)
