"""The leakage report flags test poses that repeat training configurations, and only those."""

from __future__ import annotations

import numpy as np
import torch

from torchcal.model_selection.leakage import leakage_report


def test_random_split_of_a_wrist_sweep_is_flagged_and_a_new_series_is_not(robot, generator):
    base = robot.sample_joints(150, generator, margin=0.2)
    q = base.repeat_interleave(4, 0).clone()
    q[:, -1] += torch.deg2rad(torch.arange(4, dtype=torch.float64) * 10).repeat(150)
    perm = torch.randperm(len(q), generator=generator)
    leaky = leakage_report(robot, q[perm[:480]], q[perm[480:]])
    assert leaky.twin_share > 0.5 and leaky.warning
    fresh = leakage_report(robot, q, robot.sample_joints(200, generator, margin=0.2))
    assert fresh.twin_share == 0.0 and not fresh.warning
    assert fresh.scored_to_training_median_mm > 0.5 * fresh.training_spacing_median_mm
    assert "training twin" in leaky.summary()


def test_poses_far_from_every_training_pose_are_named_extrapolation(robot, generator):
    """Trained in one corner of the joint space and scored everywhere: most scored poses are further than
    twice the training spacing from every training pose, which the report says; poses drawn like the
    training poses are not."""
    from torchcal.data.folds import joint_lever_arms, pose_embedding
    from torchcal.model_selection.leakage import far_from_training

    limits = robot.joint_limits
    span = limits[:, 1] - limits[:, 0]
    corner = limits[:, 0] + 0.2 * span * torch.rand(300, robot.dof, generator=generator, dtype=torch.float64)
    corner[:, 3:] = robot.sample_joints(300, generator)[:, 3:]  # the wrist anywhere: the arm's corner is the region
    everywhere = robot.sample_joints(300, generator, margin=0.1)
    report = leakage_report(robot, corner, everywhere)
    flags, radius = far_from_training(robot, corner, everywhere)
    # the radius is what the grouped CV scored: beyond the training spacing, within the corner's extent
    points = pose_embedding(robot, corner, joint_lever_arms(robot, corner)) * 1e3
    extent = float(np.linalg.norm(points.max(0) - points.min(0)))
    assert report.training_spacing_median_mm < radius < extent and radius == report.far_radius_mm
    assert report.far_share == float(flags.mean()) > 0.5
    assert "extrapolates" in report.warning and f"{100 * report.far_share:.0f} % of the scored poses" in report.warning
    like = limits[:, 0] + 0.2 * span * torch.rand(200, robot.dof, generator=generator, dtype=torch.float64)
    like[:, 3:] = robot.sample_joints(200, generator)[:, 3:]  # drawn as the training poses were
    near = leakage_report(robot, corner, like)
    assert near.far_share < 0.1 and "extrapolates" not in near.warning


def test_no_far_radius_where_the_poses_cannot_be_split_and_never_below_the_floor(robot, generator):
    """A handful of configurations (repeats) cannot be split into groups: nothing is called far (a radius of
    a micron called every pose far); a dense sweep's radius is at least the floor, above the twin radius."""
    import json
    import math

    from torchcal.model_selection.leakage import FAR_FLOOR_MM, LeakageReport, far_from_training

    few = robot.sample_joints(3, generator).repeat_interleave(10, 0)
    report = leakage_report(robot, few, robot.sample_joints(20, generator))
    assert math.isnan(report.far_radius_mm) and report.far_share == 0.0 and "extrapolates" not in report.warning
    assert "none within" not in report.summary()
    stored = json.loads(json.dumps(report.to_dict(), allow_nan=False))  # strict JSON: no NaN written
    assert stored["far_radius_mm"] is None and math.isnan(LeakageReport(**stored).far_radius_mm)
    flags, radius = far_from_training(robot, few[:4], robot.sample_joints(5, generator))  # 4 poses: no split at all
    assert math.isnan(radius) and not flags.any()
    # a dense sweep is one chain of twins, one group: no split either, nothing far
    sweep = robot.sample_joints(1, generator).repeat(3000, 1)
    sweep[:, 0] += torch.linspace(0.0, 1.5, 3000, dtype=torch.float64)
    assert math.isnan(leakage_report(robot, sweep, robot.sample_joints(20, generator)).far_radius_mm)
    spread = leakage_report(robot, robot.sample_joints(200, generator), robot.sample_joints(20, generator))
    assert spread.far_radius_mm >= FAR_FLOOR_MM and spread.far_radius_mm > spread.training_spacing_median_mm
