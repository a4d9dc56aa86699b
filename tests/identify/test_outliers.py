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
