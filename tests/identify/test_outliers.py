"""Rows the geometry cannot explain are found (and only they), on a twin whose rows were damaged on purpose."""

from __future__ import annotations

import math
import warnings
from dataclasses import replace

import pytest
import torch

from torchcal.core.errors import DataError, IdentifiabilityWarning
from torchcal.identify.outliers import find_outlier_rows
from torchcal.sim.twin import Twin, TwinConfig


@pytest.fixture(scope="module")
def twin_data():
    twin = Twin.create(TwinConfig(n_train=60, gravity=False, gear=False))
    data = twin.sample(60, torch.Generator().manual_seed(3))
    return twin.robot, data


def _with_q_offset(data, rows, deg):
    q = data.q.clone()
    q[rows, 1] += math.radians(deg)  # a slipped digit in joint 2
    return replace(data, q=q)


def test_clean_twin_rows_are_all_kept(twin_data):
    robot, data = twin_data
    assert find_outlier_rows(robot, data, parallel_threshold_deg=2.0) is None


def test_the_screening_fit_leaves_identifiability_to_the_fit_proper(twin_data):
    # its rank cut would say "stay at nominal" beside the prior fit's "stay at their prior"
    robot, data = twin_data
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        find_outlier_rows(robot, data, parallel_threshold_deg=2.0)
    assert not [w for w in caught if issubclass(w.category, IdentifiabilityWarning)]


def test_mistyped_angles_are_found_and_named(twin_data):
    robot, data = twin_data
    damaged = _with_q_offset(data, [4, 17, 41], 5.0)
    found = find_outlier_rows(robot, damaged, parallel_threshold_deg=2.0)
    assert found is not None and found.index == (4, 17, 41)
    assert min(found.errors_mm) > 10 * found.median_mm
    assert "left out of the fit" in found.message("train.csv")


def test_a_file_with_many_bad_rows_is_refused(twin_data):
    robot, data = twin_data
    damaged = _with_q_offset(data, list(range(0, 60, 4)), 5.0)  # a quarter of the rows: not a few slips
    with pytest.raises(DataError, match="mixes set-ups"):
        find_outlier_rows(robot, damaged, parallel_threshold_deg=2.0)


PROBE = torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64)  # a 6-D probe's rotation on the flange (rotation vector)


def _with_orientation(twin_data_6d, rows=(), deg=0.0):
    """The twin's poses with the probe's measured orientation, ``rows`` turned by ``deg`` about x (a bad rx)."""
    twin, data = twin_data_6d
    from torchcal.kinematics import transforms as tf

    flange = twin.T_instrument_base() @ twin.model.base_flange_pose(data.q, twin.x_true)
    rotation = flange[..., :3, :3] @ tf.so3_exp(PROBE)
    if rows:
        slip = tf.so3_exp(torch.tensor([math.radians(deg), 0.0, 0.0], dtype=torch.float64))
        rotation[list(rows)] = slip @ rotation[list(rows)]
    return replace(data, rotation=rotation)


@pytest.fixture(scope="module")
def twin_data_6d():
    twin = Twin.create(TwinConfig(n_train=60, gravity=False, gear=False))
    return twin, twin.sample(60, torch.Generator().manual_seed(3))


def test_a_mistyped_orientation_row_is_found_and_named_and_clean_ones_are_kept(twin_data_6d):
    from torchcal.identify.outliers import find_orientation_outlier_rows

    twin, data = twin_data_6d
    assert find_orientation_outlier_rows(twin.robot, data, parallel_threshold_deg=2.0) is None  # positions only
    assert find_orientation_outlier_rows(twin.robot, _with_orientation(twin_data_6d), parallel_threshold_deg=2.0) is None
    found = find_orientation_outlier_rows(twin.robot, _with_orientation(twin_data_6d, (22,), 30.0), parallel_threshold_deg=2.0)
    assert found is not None and found.index == (22,) and found.angles_deg[0] == pytest.approx(30.0, abs=1.0)
    assert "orientation (rx, ry, rz)" in found.message("six.csv") and "left out of the fit" in found.message("six.csv")
    with pytest.raises(DataError, match="rx, ry, rz convention"):
        find_orientation_outlier_rows(twin.robot, _with_orientation(twin_data_6d, tuple(range(0, 60, 4)), 30.0),
                                      parallel_threshold_deg=2.0)
