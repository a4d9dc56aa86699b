"""The prior's strength: the evidence's tie rule on fixed log evidences, and the grouped cross-validation's choice."""

from __future__ import annotations

import math
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from tests.identify.test_prior import _in_model_twin
from torchcal.data.folds import make_folds
from torchcal.identify.calibrate import calibrate
from torchcal.identify.prior import PriorSpec
from torchcal.model_selection.prior_scale import (
    cross_validate_prior_scales,
    evidence_prior_scales,
    selection_record,
)

LABELS = ["nominal", "prior x0.25", "prior x1", "prior x4", "prior x16"]


def _evidence_choice(log_evidence: dict[str, float]):
    """The evidence selection with each candidate's fit stubbed by its fixed log evidence."""
    calls = []

    def fitter(spec):
        def fit(data, start=None):
            calls.append(spec.label())
            return SimpleNamespace(log_evidence=log_evidence[spec.label()], noise_sigma_m=2e-5)
        return fit

    chosen, record, full = evidence_prior_scales(fitter, PriorSpec(), list(range(50)))
    assert calls == LABELS  # simplest first, one fit each
    assert full.log_evidence == log_evidence[chosen.label()]
    return chosen, record


@pytest.mark.parametrize(("evidence", "expected"), [
    # x1 the most probable, x0.25 1.05 nats below it (a Bayes factor 2.9 < 3): the simpler one
    ({"nominal": -500.0, "prior x0.25": 10.0, "prior x1": 11.05, "prior x4": 9.0, "prior x16": 2.0}, "prior x0.25"),
    # 1.15 nats apart (a Bayes factor 3.2): the better one
    ({"nominal": -500.0, "prior x0.25": 10.0, "prior x1": 11.15, "prior x4": 9.0, "prior x16": 2.0}, "prior x1"),
    # the most complex is best; x4 within 1.0, x1 1.2 beyond: x4, not x1
    ({"nominal": -500.0, "prior x0.25": 5.0, "prior x1": 8.8, "prior x4": 9.0, "prior x16": 10.0}, "prior x4"),
    # the nominal robot within the tie of the best: not calibrating is kept
    ({"nominal": 3.0, "prior x0.25": 4.0, "prior x1": 3.5, "prior x4": 1.0, "prior x16": -1.0}, "nominal"),
])
def test_evidence_keeps_the_simplest_candidate_within_ln3_nats_of_the_most_probable(evidence, expected):
    chosen, record = _evidence_choice(evidence)
    assert chosen.label() == expected and record["chosen"] == expected
    assert chosen.scale == {"nominal": 0.0, "prior x0.25": 0.25, "prior x1": 1.0, "prior x4": 4.0,
                            "prior x16": 16.0}[expected] == record["scale"]
    best = max(evidence.values())
    assert [c["name"] for c in record["candidates"]] == LABELS
    for c in record["candidates"]:
        assert c["delta_log_evidence"] == pytest.approx(evidence[c["name"]] - best)
        assert c["verdict"] == ("chosen" if c["name"] == expected else "")
    assert record["method"] == "evidence"


def _held_out_rule(errors: dict[str, np.ndarray], units: np.ndarray, tolerance: float = 0.01) -> str:
    """docs/prior.md and model_selection/compare.py, by hand: the simplest candidate whose mean squared held-out
    error exceeds the best's by no more than one standard error of the paired difference (over the configuration
    regions) or 1 % in RMS."""
    rms = {n: math.sqrt(float(np.mean(e**2))) for n, e in errors.items()}
    best = min(rms, key=rms.get)
    for name in LABELS:
        d = errors[name] ** 2 - errors[best] ** 2
        per_region = np.array([d[units == u].sum() - (units == u).sum() * d.mean() for u in np.unique(units)])
        g = len(per_region)
        se = math.sqrt(g / (g - 1) * float(np.sum(per_region**2))) / len(d)
        if d.mean() <= max(se, ((1 + tolerance) ** 2 - 1) * rms[best] ** 2):
            return name
    raise AssertionError("the best is always within noise of itself")


def test_cross_validated_prior_scale_calibrates_a_robot_with_errors_and_keeps_the_rule():
    """prior_scale=cv on a twin with tolerance-sized geometric errors: the nominal robot is far worse held out and
    not chosen; the choice is the candidate the documented rule picks from the held-out errors, recomputed here
    from each fold's fit."""
    twin, train, _ = _in_model_twin(4, 80)
    folds = make_folds("grouped", twin.robot, train.q, k=4, seed=0)
    fits = {}

    def fitter(spec):
        def fit(part):
            result = calibrate(twin.robot, part, prior=spec)
            fits[spec.label(), part.q.numpy().tobytes()] = result
            return result
        return fit

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        chosen, comparison, fold_fits = cross_validate_prior_scales(train, fitter, PriorSpec(), folds)
    record = selection_record(comparison, chosen)
    # every pose's held-out error, from the fit of the folds that did not see it
    errors = {name: np.full(len(train), np.nan) for name in LABELS}
    for train_idx, test_idx in folds.splits():
        part, held = train.subset(train_idx), train.subset(test_idx)
        for name in LABELS:
            result = fits[name, part.q.numpy().tobytes()]
            predicted = result.model.tcp_position(held.q, result.x).detach()
            errors[name][test_idx] = (held.position - predicted).norm(dim=-1).numpy() * 1e3
    assert not np.isnan(np.concatenate(list(errors.values()))).any()
    rms = {n: math.sqrt(float(np.mean(e**2))) for n, e in errors.items()}
    assert record["method"] == "cv"
    assert [c["name"] for c in record["candidates"]] == LABELS
    for c in record["candidates"]:
        assert c["cv_rms_mm"] == pytest.approx(rms[c["name"]], rel=1e-9), c
    # the twin's errors (0.3 mm / 0.03 deg) are many times its noise (0.025 mm RMS): calibrating pays
    assert rms["nominal"] > 10 * min(rms.values())
    assert not chosen.nominal and record["chosen"] != "nominal"
    assert record["chosen"] == chosen.label() == _held_out_rule(errors, folds.units())
    assert record["scale"] == chosen.scale
    # the chosen spec's per-fold fits come back for the structure cross-validation to reuse
    assert len(fold_fits) == folds.k and all(f.prior.spec.scale == chosen.scale for f in fold_fits.values())
