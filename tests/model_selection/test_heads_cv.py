"""Cross-validation pieces fitted side by side in worker processes give what one process gives, to
the bit: the structure folds (errors and fits) and the heads (out-of-fold errors, futility stops)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcal.config.schema import FitConfig
from torchcal.core.workers import ready_workers, warm_up
from torchcal.model_selection.heads import cross_validate_heads
from torchcal.model_selection.structure import cross_validate_structures
from torchcal.residual import MayflyELM, MLPHead
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit_with_selection, geometry_fitter, make_config_folds
from torchcal.stages.prior_options import base_spec


@pytest.fixture(scope="module")
def fitted():
    twin = Twin.create(TwinConfig(seed=3, gravity=True, gear=True))
    data = twin.sample(300, torch.Generator().manual_seed(5))
    config = FitConfig(progress=False, gravity_compliance="none", joint_harmonics="none", residual="mma-elm+mlp",
                       cv_folds=3, prior_scale="1")
    _result, structure = fit_with_selection(twin.robot, data, config)
    warm_up(2, ["torchcal.model_selection.heads"], wait=True)
    return twin, data, config, structure


def test_structure_folds_side_by_side_give_exactly_the_serial_fits(fitted):
    twin, data, config, _structure = fitted
    # three options: a fold's options go out in two unequal halves ({1st, 3rd}, {2nd}) and come back in place
    options = [("none", "none"), ("wrist", "none"), ("elbow+wrist", "none")]
    folds = make_config_folds(twin.robot, data, config)
    geometry = geometry_fitter(twin.robot, config, base_spec(twin.robot, config))
    serial = cross_validate_structures(twin.robot, data, geometry, options, folds, jobs=1)
    assert ready_workers() == 1
    parallel = cross_validate_structures(twin.robot, data, geometry, options, folds, jobs=2)
    for label in serial.error_vectors_mm:
        np.testing.assert_array_equal(parallel.error_vectors_mm[label], serial.error_vectors_mm[label])
        for p, s in zip(parallel.fold_results[label], serial.fold_results[label]):
            assert torch.equal(p.x, s.x)
    assert parallel.comparison.chosen == serial.comparison.chosen


@pytest.mark.slow
def test_heads_side_by_side_give_exactly_the_serial_errors(fitted):
    twin, data, _config, structure = fitted
    parent = structure.comparison.chosen

    def heads():  # small ones: what is compared is where they are fitted, not how well
        return [MayflyELM(hidden=20, population=6, iterations=4, seed=1), MLPHead(width=16, max_epochs=30, patience=10)]

    serial = cross_validate_heads(twin.robot, data, structure, parent, heads, margin=0.05, jobs=1)
    assert ready_workers() == 1
    parallel = cross_validate_heads(twin.robot, data, structure, parent, heads, margin=0.05, jobs=2)
    assert parallel.stopped == serial.stopped
    assert [c.name for c in parallel.candidates] == [c.name for c in serial.candidates]
    for p, s in zip(parallel.candidates, serial.candidates):
        np.testing.assert_array_equal(p.errors_mm, s.errors_mm)
    # the heads were fitted and scored: finite out-of-fold errors on every pose of a fold they ran
    for c in serial.candidates:
        assert np.isfinite(c.errors_mm).all()
    assert len(serial.candidates) + len(serial.stopped) == 2
