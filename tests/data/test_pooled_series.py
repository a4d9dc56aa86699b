"""Pooled measurement series (data.series) and their folds (data.folds.series_folds)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcal.core.errors import DataError
from torchcal.data.folds import make_folds
from torchcal.data.measurements import Measurements
from torchcal.data.series import pool_series, series_count, split_series
from torchcal.kinematics.robot import load_robot
from torchcal.sim.twin import default_robot_path


@pytest.fixture(scope="module")
def robot():
    return load_robot(default_robot_path())


def _series(robot, n: int, seed: int, source: str) -> Measurements:
    q = robot.sample_joints(n, torch.Generator().manual_seed(seed))
    return Measurements(q=q, position=robot.tcp_position(q), source=source, line_numbers=tuple(range(2, n + 2)),
                        sha256=source * 8)


def test_pool_keeps_each_series_and_splits_back(robot):
    a, b = _series(robot, 30, 1, "a.csv"), _series(robot, 20, 2, "b.csv")
    pooled = pool_series([a, b])
    assert len(pooled) == 50 and series_count(pooled) == 2 and pooled.source == "a.csv + b.csv"
    back = split_series(pooled)
    assert torch.equal(back[1].q, b.q) and back[1].line_numbers == b.line_numbers
    assert series_count(pooled.subset([0, 1, 45])) == 2 and pooled.subset([0, 45]).series.tolist() == [0, 1]
    with pytest.raises(DataError, match="joints"):
        pool_series([a, Measurements(q=a.q[:, :5], position=a.position)])


def test_grouped_folds_keep_regions_within_a_series_and_hold_out_every_series(robot):
    a, b = _series(robot, 300, 1, "a.csv"), _series(robot, 200, 2, "b.csv")
    pooled = pool_series([a, b])
    folds = make_folds("grouped", robot, pooled.q, k=5, series=pooled.series)
    series = pooled.series.numpy()
    assert folds.groups is not None
    for g in np.unique(folds.groups):  # no region straddles two series
        assert len(np.unique(series[folds.groups == g])) == 1
    for f in range(5):  # every held-out fold holds about a fifth of each series
        for s in (0, 1):
            share = np.mean(folds.fold[series == s] == f)
            assert 0.1 < share < 0.3, (f, s, share)
    assert "within each of 2 series" in folds.description


def test_blocks_cut_each_series_in_its_own_order(robot):
    a, b = _series(robot, 50, 1, "a.csv"), _series(robot, 30, 2, "b.csv")
    pooled = pool_series([a, b])
    folds = make_folds("blocks", robot, pooled.q, k=5, order=np.asarray(pooled.line_numbers), series=pooled.series)
    assert folds.fold[:50].tolist() == sorted(folds.fold[:50].tolist())  # contiguous within series a
    assert folds.fold[50:].tolist() == [i * 5 // 30 for i in range(30)]  # and within b, from its first row
    with pytest.raises(DataError, match="each series"):
        make_folds("blocks", robot, pool_series([a, b.subset(list(range(6)))]).q, k=5,
                   series=pool_series([a, b.subset(list(range(6)))]).series)


def test_a_series_given_twice_or_a_row_pasted_across_series_is_refused(robot):
    a, b = _series(robot, 30, 1, "a.csv"), _series(robot, 20, 2, "b.csv")
    copy = Measurements(q=a.q, position=a.position, source="copy.csv", line_numbers=a.line_numbers, sha256=a.sha256)
    with pytest.raises(DataError, match=r"same content as a\.csv"):
        pool_series([a, copy])
    pasted = Measurements(q=torch.cat([b.q, a.q[7:8]]), position=torch.cat([b.position, a.position[7:8]]),
                          source="b2.csv", line_numbers=tuple(range(2, 23)), sha256="b2" * 32)
    with pytest.raises(DataError, match=r"b2.csv, row 22.*copies row 9 of a.csv"):
        pool_series([a, pasted])


def test_series_with_different_columns_name_the_file_that_has_them(robot):
    a = _series(robot, 30, 1, "a.csv")
    six_d = Measurements(q=a.q, position=a.position + 0.1, rotation=torch.eye(3, dtype=torch.float64).expand(30, 3, 3),
                         source="six_d.csv", line_numbers=a.line_numbers, sha256="6d" * 32)
    for order in ([six_d, a], [a, six_d]):
        with pytest.raises(DataError, match=r"six_d\.csv has rotation, a\.csv does not"):
            pool_series(order)
