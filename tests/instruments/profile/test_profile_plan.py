"""Motion planning for the profile sensor: reachable, in range, non-degenerate; clear refusals."""

from __future__ import annotations

import math

import pytest
import torch

from torchcal.core.errors import TorchcalError
from torchcal.instruments.profile.closed_form import group_scans
from torchcal.instruments.profile.plan import (
    PlanConfig,
    SensorRange,
    plan_profile_scans,
    visible_share,
)
from torchcal.instruments.profile.twin import ProfileTwin, ProfileTwinConfig
from torchcal.kinematics import transforms as tf


@pytest.fixture(scope="module")
def twin():
    return ProfileTwin(ProfileTwinConfig(seed=6, points_per_scan=20))


def test_plan_is_reachable_and_matches_its_poses(twin):
    plan = twin.plan
    assert bool(twin.robot.within_limits(plan.q).all())
    torch.testing.assert_close(twin.robot.flange_pose(plan.q), plan.T_base_flange, rtol=0, atol=1e-9)
    for k in range(3):
        kinds = [kd for kd, p in zip(plan.kinds, plan.plane.tolist()) if p == k]
        assert kinds == ["reference"] + ["translation"] * 4 + ["rotation"] * 6


def test_plan_keeps_the_line_in_the_window_and_the_motions_sound(twin):
    plan, c = twin.plan, twin.config
    T_bs = plan.T_base_flange @ tf.homogeneous(twin.R_design, twin.t_design)
    for j in range(len(plan.kinds)):
        k = int(plan.plane[j])
        assert float(visible_share(T_bs[j], twin.normals[k], twin.points[k], c.window)) >= PlanConfig().min_visible
    groups = [g for g in group_scans(plan.T_base_flange, plan.plane) if len(g.scans) > 1]
    assert len(groups) == 3 and all(g.non_coplanar for g in groups)
    rot = [math.degrees(float(m.norm())) for m, kd in zip(plan.motions, plan.kinds) if kd == "rotation"]
    assert all(0 < r <= c.rotation_deg + 1e-9 for r in rot)


def test_rotations_are_about_the_centre_of_view(twin):
    plan, c = twin.plan, twin.config
    T_bs = plan.T_base_flange @ tf.homogeneous(twin.R_design, twin.t_design)
    centre = T_bs[:, :3, :3] @ torch.tensor([0, 0, c.window.w_mid], dtype=torch.float64) + T_bs[:, :3, 3]
    for j, kind in enumerate(plan.kinds):
        if kind == "rotation":
            ref = [i for i in range(j) if plan.kinds[i] == "reference"][-1]
            torch.testing.assert_close(centre[j], centre[ref], rtol=0, atol=1e-9)


def test_refusals(twin, robot):
    args = (robot, twin.normals, twin.points, twin.R_design, twin.t_design)
    with pytest.raises(TorchcalError, match=">= 3 pure translations"):
        plan_profile_scans(*args, config=PlanConfig(n_translations=2))
    with pytest.raises(TorchcalError, match=">= 2 non-parallel axes"):
        plan_profile_scans(*args, config=PlanConfig(n_rotations=1))
    with pytest.raises(TorchcalError, match=">= 3 placements"):
        plan_profile_scans(robot, twin.normals[:2], twin.points[:2], twin.R_design, twin.t_design)
    far = twin.points + torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64)
    with pytest.raises(TorchcalError, match="not reachable"):
        plan_profile_scans(robot, twin.normals, far, twin.R_design, twin.t_design, config=PlanConfig(ik_starts=8))
    down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand(3, 3)
    with pytest.raises(TorchcalError, match="leaves the w window"):
        plan_profile_scans(robot, twin.normals, twin.points, twin.R_design, twin.t_design,
                           SensorRange(-0.025, 0.025, 0.119, 0.121), view_directions=down)
