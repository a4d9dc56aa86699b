"""The leakage report flags test poses that repeat training configurations, and only those."""

from __future__ import annotations

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
