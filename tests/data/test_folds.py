"""Folds: near-twins stay together, blocks are contiguous, the embedding measures tool motion."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcal.core.errors import DataError
from torchcal.data.folds import joint_lever_arms, make_folds, pose_embedding


def _wrist_sweep(robot, generator, n_base=60, steps=5):
    """``n_base`` configurations, each repeated with the last joint swept in 10 deg steps (tool on its axis)."""
    base = robot.sample_joints(n_base, generator, margin=0.2)
    q = base.repeat_interleave(steps, 0).clone()
    q[:, -1] = q[:, -1] + torch.deg2rad(torch.arange(steps, dtype=torch.float64) * 10.0).repeat(n_base)
    return q, np.repeat(np.arange(n_base), steps)


def test_embedding_distance_is_tool_motion_for_small_steps(robot, generator):
    q = robot.sample_joints(200, generator, margin=0.2)
    arms = joint_lever_arms(robot, q)
    step = torch.zeros_like(q)
    step[:, 1] = 1e-3  # one joint moves: the embedding distance is its lever arm (RMS over poses) x 1 mrad
    d = np.linalg.norm(pose_embedding(robot, q + step, arms) - pose_embedding(robot, q, arms), axis=1)
    true_motion = (robot.tcp_position(q + step) - robot.tcp_position(q)).norm(dim=-1).numpy()
    assert np.sqrt(np.mean(d**2)) == pytest.approx(np.sqrt(np.mean(true_motion**2)), rel=1e-3)


def test_wrist_roll_has_no_lever_when_the_tool_is_on_its_axis(robot, generator):
    q = robot.sample_joints(100, generator)
    arms = joint_lever_arms(robot, q)
    tool = robot.tool[:2].norm().item()
    assert arms[-1] == pytest.approx(tool, abs=1e-6)  # tool (0, 0, 100 mm): on the axis
    assert arms[:3].min() > 0.1


def test_grouped_folds_keep_wrist_twins_together(robot, generator):
    q, config_id = _wrist_sweep(robot, generator)
    folds = make_folds("grouped", robot, q, k=5, seed=0)
    for c in np.unique(config_id):
        assert len(set(folds.fold[config_id == c].tolist())) == 1
    random = make_folds("random", robot, q, k=5, seed=0)
    split_twins = sum(len(set(random.fold[config_id == c].tolist())) > 1 for c in np.unique(config_id))
    assert split_twins > 50  # the random split separates almost every twin set: what grouping prevents
    assert folds.k == 5 and np.bincount(folds.fold).min() > 0.5 * len(q) / 5


def test_block_folds_are_contiguous_in_order():
    order = np.array([5, 3, 9, 0, 1, 2, 8, 7, 6, 4, 11, 10])
    folds = make_folds("blocks", None, torch.zeros(12, 6), k=3, order=order)
    by_order = folds.fold[np.argsort(order)]
    assert by_order.tolist() == [0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]


def test_bad_split_and_too_few_poses_are_refused(robot, generator):
    q = robot.sample_joints(8, generator)
    with pytest.raises(DataError, match="unknown split"):
        make_folds("rows", robot, q)
    with pytest.raises(DataError, match="at least 10 poses"):
        make_folds("grouped", robot, q, k=5)
    same = q[:1].repeat(12, 1)
    with pytest.raises(DataError, match="configuration groups"):
        make_folds("grouped", robot, same, k=5)


def test_units_are_groups_for_grouped_folds(robot, generator):
    q, _ = _wrist_sweep(robot, generator, n_base=30)
    folds = make_folds("grouped", robot, q)
    assert folds.units() is folds.groups
    assert len(np.unique(folds.groups)) <= 20
    assert math.isclose(len(make_folds("random", robot, q).units()), len(q))


def _grouped(robot, q):
    folds = make_folds("grouped", robot, q, k=5, seed=3)
    return folds.fold, folds.groups


def test_grouped_folds_are_the_same_made_in_a_worker(robot, generator):
    """A fit's folds may be made by a worker process (one OpenMP thread) while the fit goes on: the
    same folds as here, whatever the threads k-means would otherwise take."""
    from threadpoolctl import threadpool_limits

    from torchcal.core.workers import side_by_side, stop_workers, warm_up

    q = robot.sample_joints(600, generator)
    warm_up(2, ["torchcal.data.folds"], wait=True)
    try:
        here, there = side_by_side(_grouped, [(robot, q), (robot, q)], 2)
    finally:
        stop_workers()
    with threadpool_limits(2):
        two_threads = _grouped(robot, q)
    for a, b, c in zip(here, there, two_threads, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


def test_each_split_names_its_own_protocol(robot, generator):
    q = robot.sample_joints(200, generator)
    labels = {kind: make_folds(kind, robot, q, k=5).label for kind in ("grouped", "blocks", "random")}
    assert labels == {"grouped": "5-fold grouped cross-validation",
                      "blocks": "5-fold blocked (contiguous measurement order) cross-validation",
                      "random": "5-fold random-row cross-validation"}
