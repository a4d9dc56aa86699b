"""Cross-validation pieces fitted side by side in worker processes give what one process gives, to
the bit: the structure folds (errors and fits) and the heads (out-of-fold errors, futility stops); and the
futility stop itself, against held-out RMS recomputed in numpy."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import torch

from tests.model_selection.drift_twin import geometric_twin, smooth_field_series
from torchcal.config.schema import FitConfig
from torchcal.core.workers import ready_workers, warm_up
from torchcal.model_selection.heads import cross_validate_heads
from torchcal.model_selection.structure import cross_validate_structures, fold_targets
from torchcal.residual import MayflyELM, MLPHead
from torchcal.residual.base import ResidualHead
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


# -- the futility stop: a head that learns nothing stops after its first fold, one that learns does not

class FieldBasisHead(ResidualHead):
    """Least squares (plus a constant) on the basis of ``drift_twin``'s smooth field, built from the
    head features' ``sin q`` and ``cos q`` columns; its prediction times ``shrink``. Every fit's pose
    count goes to ``fits`` (a head that tunes nothing fits all of a fold's training poses)."""

    tunes_on_validation = False

    def __init__(self, name: str, fits: list[int], shrink: float = 1.0) -> None:
        self.name, self.fits, self.shrink = name, fits, shrink

    @staticmethod
    def basis(s: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return torch.stack([torch.ones_like(s[:, 0]), s[:, 0] * c[:, 1], c[:, 1] * c[:, 2] - s[:, 1] * s[:, 2],
                            s[:, 1] * s[:, 2]], -1)

    def fit(self, x_train, y_train, x_val=None, y_val=None):
        self.fits.append(len(x_train))
        n = x_train.shape[1] // 3
        b = self.basis(x_train[:, n:2 * n], x_train[:, 2 * n:])
        self.coef = torch.linalg.lstsq(b, y_train).solution * self.shrink
        return self

    def module(self):
        coef, basis = self.coef, self.basis

        class Basis(torch.nn.Module):
            def forward(self, x):
                n = x.shape[1] // 3
                return basis(x[:, n:2 * n], x[:, 2 * n:]) @ coef.to(x.dtype)

        return Basis()

    def settings(self):
        return {}


STOP = re.compile(r"^stopped after 1 of 3 folds: held-out RMS (\d+\.\d{4}) mm vs (\d+\.\d{4}) mm without it on those "
                  r"poses \(gain below 2\.5 %\)$")


def first_fold_rms(data, structure, parent, shrink: float) -> tuple[float, float]:
    """``(head, geometry)`` held-out RMS (mm) on fold 1's poses, recomputed in numpy: the field basis from
    ``sin q, cos q`` of the joints, fitted by ``numpy.linalg.lstsq`` on fold 1's training poses."""
    train, test = structure.folds.splits()[0]
    q = data.q.numpy()

    def basis(i):
        s, c = np.sin(q[i]), np.cos(q[i])
        return np.stack([np.ones(len(i)), s[:, 0] * c[:, 1], np.cos(q[i, 1] + q[i, 2]), s[:, 1] * s[:, 2]], -1)

    result = structure.fold_results[parent][0]
    y_train, y_test = (fold_targets(result, data, i).numpy() for i in (train, test))
    coef = np.linalg.lstsq(basis(train), y_train, rcond=None)[0] * shrink
    head = np.sqrt(np.mean(np.sum((y_test - basis(test) @ coef) ** 2, axis=1)))
    parent_errors = next(c.errors_mm for c in structure.candidates if c.name == parent)
    return float(head), float(np.sqrt(np.mean(parent_errors[test] ** 2)))


@pytest.fixture(scope="module")
def futility_cases():
    """Structure CV (geometry only, 3 folds) of 150 poses of a geometric twin: pure noise after the fit,
    and the same with ``drift_twin``'s smooth 0.3 mm field added, which no geometric parameter expresses."""
    twin = geometric_twin()
    config = FitConfig(progress=False, gravity_compliance="none", joint_harmonics="none", residual="none",
                       cv_folds=3, prior_scale="1")
    cases = {"noise": twin.sample(150, torch.Generator().manual_seed(1)),
             "field": smooth_field_series(twin, 150, torch.Generator().manual_seed(2))}
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the rank diagnostic of a geometry-only fit
        for name, data in cases.items():
            _result, structure = fit_with_selection(twin.robot, data, config)
            assert structure.folds.k == 3
            out[name] = (data, structure, structure.comparison.chosen)
    return twin, config.residual_margin, out


def test_futility_stops_heads_on_pure_noise_after_the_first_fold(futility_cases):
    twin, margin, cases = futility_cases
    data, structure, parent = cases["noise"]
    fits: list[int] = []

    def heads():
        return [FieldBasisHead("basis", fits), MayflyELM(hidden=20, population=6, iterations=4, seed=1)]

    out = cross_validate_heads(twin.robot, data, structure, parent, heads, margin=margin)
    assert out.candidates == [] and sorted(out.stopped) == ["basis", "mma-elm"]
    n_train_first = len(structure.folds.splits()[0][0])
    assert fits == [n_train_first]  # fitted on fold 1 only, then never again
    head_rms, base_rms = first_fold_rms(data, structure, parent, 1.0)
    assert head_rms > (1 - margin / 2) * base_rms  # the truth: on noise the head gains nothing
    for reason in out.stopped.values():
        named = STOP.match(reason)
        assert named, reason
        assert float(named[2]) == pytest.approx(base_rms, abs=5.1e-5)
        assert float(named[1]) > (1 - margin / 2) * float(named[2])
    assert float(STOP.match(out.stopped["basis"])[1]) == pytest.approx(head_rms, abs=5.1e-5)


def test_futility_keeps_heads_that_learn_a_smooth_residual(futility_cases):
    """The field basis fitted whole gains far more than ``margin`` (the geometry absorbs part of the
    field, the basis explains about half of what is left); shrunk to 8 % of its fit it gains less than
    ``margin`` but more than ``margin / 2``: kept; shrunk to 1 % it gains below ``margin / 2``: stopped."""
    twin, margin, cases = futility_cases
    data, structure, parent = cases["field"]
    shrink = {"whole": 1.0, "part": 0.08, "trace": 0.01}
    fits: dict[str, list[int]] = {name: [] for name in shrink}

    def heads():
        return [FieldBasisHead(name, fits[name], s) for name, s in shrink.items()]

    out = cross_validate_heads(twin.robot, data, structure, parent, heads, margin=margin)
    # the truth on fold 1, recomputed: where each head stands against the stopping line
    base = first_fold_rms(data, structure, parent, 1.0)[1]
    gain = {name: 1 - first_fold_rms(data, structure, parent, s)[0] / base for name, s in shrink.items()}
    assert gain["whole"] > 0.3
    assert margin / 2 + 0.01 < gain["part"] < margin and gain["trace"] < margin / 2 - 0.01
    assert [c.name for c in out.candidates] == [f"{parent}+whole", f"{parent}+part"]
    assert list(out.stopped) == ["trace"]
    named = STOP.match(out.stopped["trace"])
    assert named, out.stopped["trace"]
    assert float(named[1]) == pytest.approx(base * (1 - gain["trace"]), abs=5.1e-5)
    assert float(named[2]) == pytest.approx(base, abs=5.1e-5)
    n_train = [len(train) for train, _ in structure.folds.splits()]
    assert fits["whole"] == n_train and fits["part"] == n_train and fits["trace"] == n_train[:1]
    parent_errors = next(c.errors_mm for c in structure.candidates if c.name == parent)
    whole = out.candidates[0]
    assert whole.parent == parent and whole.head == "whole" and np.isfinite(whole.errors_mm).all()
    assert np.sqrt(np.mean(whole.errors_mm ** 2)) < 0.7 * np.sqrt(np.mean(parent_errors ** 2))
