"""The profile twin: contract files, truth, noise statistics, repeatability."""

from __future__ import annotations

import json
import math

import torch

from torchcal.instruments.profile.data import load_profile
from torchcal.instruments.profile.twin import ProfileTwin, ProfileTwinConfig, write_profile_case
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.robot import load_robot


def _true_w(twin: ProfileTwin, data, T_base_flange):
    """Depth of the true line at each point's u (sensor-frame plane intersection)."""
    T_bs = T_base_flange @ tf.homogeneous(twin.R_true, twin.t_true)
    n = twin.normals[data.plane]
    k = (T_bs[:, :3, :3].transpose(-1, -2) @ n.unsqueeze(-1)).squeeze(-1)
    d = twin.offsets[data.plane] - (n * T_bs[:, :3, 3]).sum(-1)
    s = data.point_scan
    return (d[s] - k[s, 0] * data.uw[:, 0]) / k[s, 2]


def test_case_files_are_contract_files(tmp_path):
    cfg = ProfileTwinConfig(seed=3, points_per_scan=25)
    paths = write_profile_case(tmp_path, cfg)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["profile.csv", "robot.yaml", "truth.json"]
    assert paths["profile.csv"].read_text().splitlines()[0] == "scan,q1,q2,q3,q4,q5,q6,u,w,plane"
    robot = load_robot(paths["robot.yaml"])
    data = load_profile(paths["profile.csv"], n_joints=6, joint_limits_rad=robot.joint_limits)
    truth = json.loads(paths["truth.json"].read_text())
    R = torch.tensor(truth["R_flange_sensor"], dtype=torch.float64)
    torch.testing.assert_close(R.T @ R, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-12)
    assert math.isclose(float(torch.det(R)), 1.0, abs_tol=1e-12)
    assert data.n_planes == 3 and data.n_scans == 3 * (1 + cfg.n_translations + cfg.n_rotations)
    twin = ProfileTwin(cfg)
    torch.testing.assert_close(torch.tensor(truth["t_flange_sensor_mm"], dtype=torch.float64), twin.t_true * 1e3)
    # the points lie in the window and on the true planes (to the file's rounding plus noise)
    uw = data.uw * 1e3
    assert float(uw[:, 1].min()) >= cfg.w_min_mm - 0.1 and float(uw[:, 1].max()) <= cfg.w_max_mm + 0.1
    assert float(uw[:, 0].min()) >= cfg.u_min_mm and float(uw[:, 0].max()) <= cfg.u_max_mm


def test_depth_noise_has_the_configured_sigma():
    twin = ProfileTwin(ProfileTwinConfig(seed=2, points_per_scan=400, noise_w_mm=0.02))
    data = twin.scan()
    err = (data.uw[:, 1] - _true_w(twin, data, twin.robot.flange_pose(data.q))) * 1e3
    assert abs(float(err.std()) / 0.02 - 1) < 0.03 and abs(float(err.mean())) < 0.002
    clean = ProfileTwin(ProfileTwinConfig(seed=2, points_per_scan=50, noise_w_mm=0.0)).scan()
    assert float((clean.uw[:, 1] - _true_w(twin, clean, twin.robot.flange_pose(clean.q))).abs().max()) < 1e-12


def test_repeatability_moves_the_true_flange_poses():
    cfg = ProfileTwinConfig(seed=2, points_per_scan=50, noise_w_mm=0.0, repeatability_mm=0.05, repeatability_deg=0.01)
    twin = ProfileTwin(cfg)
    gen = torch.Generator().manual_seed(0)
    T = twin.true_flange_poses(gen)
    nominal = twin.robot.flange_pose(twin.plan.q)
    dp = (T[:, :3, 3] - nominal[:, :3, 3]) * 1e3
    assert 0.02 < float(dp.pow(2).mean().sqrt()) < 0.09
    angles = tf.so3_log(T[:, :3, :3] @ nominal[:, :3, :3].transpose(-1, -2)).norm(dim=-1)
    assert 0.003 < math.degrees(float(angles.pow(2).mean().sqrt())) / math.sqrt(3) < 0.02
