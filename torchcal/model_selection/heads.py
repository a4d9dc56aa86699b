"""Cross-validation of learned residual heads on top of the chosen structure.

On every fold the head learns the errors that fold's structure fit leaves on its training part
(each head's own tuning, Mayfly search or early stopping, on a slice of that training part) and
predicts the held-out part. Its candidate row is the held-out error after its correction; its
parent is the structure, and it is eligible only with ``residual_margin`` gain and a paired
z above 2 over configuration groups (:mod:`~torchcal.model_selection.compare`).

Heads are the expensive part of a fit. A head is stopped early (futility) when, after any fold
but the last (each fold is whole configuration regions, about a fifth of the poses), its pooled
held-out RMS so far is less than ``residual_margin / 2`` below the structure's on the same poses:
to pass the gate it would then need well over ``residual_margin`` on the remaining folds. A head
that learns something real gains on every fold and is never stopped; one that does not is
stopped as soon as that shows (docs/benchmarks.md: the default fit on 3000 UR10 poses). A
stopped head is reported as such.

The heads of one fold are independent of each other: with ``jobs > 1`` they are fitted side by side
in worker processes (:mod:`torchcal.core.workers`), each exactly as it would be fitted here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from torchcal.core.threads import fit_threads
from torchcal.core.workers import side_by_side
from torchcal.data.measurements import Measurements
from torchcal.model_selection.compare import Candidate
from torchcal.model_selection.structure import StructureCV, fold_targets
from torchcal.residual.base import ResidualHead
from torchcal.residual.features import JointFeatures
from torchcal.residual.selection import fit_before_gate

FUTILITY_AFTER_FOLDS = 1


@dataclass
class HeadCV:
    """Head candidates with full out-of-fold errors, and heads stopped for futility (with why)."""

    candidates: list[Candidate] = field(default_factory=list)
    stopped: dict[str, str] = field(default_factory=dict)


def make_features(robot, data: Measurements) -> JointFeatures:
    """Head features of ``robot``'s joints: joints only, never a file's temperature, because the
    compensator and monitor a controller runs take the joints alone (a head that needed temperature
    could be scored here and then never served)."""
    return JointFeatures(robot.turn_limits.to(torch.float64))  # one turn for a continuous joint


def fit_and_predict(head: ResidualHead, x_train: np.ndarray, y_train: np.ndarray, x_test: np.ndarray, seed: int,
                    device: str = "cpu") -> np.ndarray:
    """``head`` fitted on one fold's training part (its own tuning on a slice of it, as
    :func:`~torchcal.residual.selection.fit_before_gate` splits it), predicting the held-out part.

    Arrays in and out (features, targets and predictions in mm): a worker process can run it
    (:func:`torchcal.core.workers.side_by_side`), on one thread like the fit that sends it.
    """
    with fit_threads():
        x_fit, y_fit, x_held = (torch.from_numpy(a).to(device) for a in (x_train, y_train, x_test))
        fit_before_gate(head, x_fit, y_fit, seed=seed)
        with torch.no_grad():
            return head.predict(x_held).cpu().numpy()


def cross_validate_heads(robot, data: Measurements, structure: StructureCV, parent: str, make_heads, *,
                         margin: float, seed: int = 0, progress=None, jobs: int = 1) -> HeadCV:
    """Out-of-fold errors (mm) of each head from ``make_heads() -> [ResidualHead]`` on ``parent``'s fold fits.

    ``jobs``: processes that fit a fold's heads side by side (1: one after the other, here).
    """
    folds = structure.folds
    parent_errors = next(c.errors_mm for c in structure.candidates if c.name == parent)
    names = [h.name for h in make_heads()]
    errors = {name: np.full(len(data), np.nan) for name in names}
    active = list(names)
    out = HeadCV()
    for f, (train_idx, test_idx) in enumerate(folds.splits()):
        if not active:
            break
        if progress is not None:
            progress(f"cross-validating residual heads ({', '.join(active)}): fold {f + 1} of {folds.k}")
        result = structure.fold_results[parent][f]
        features = make_features(robot, data.subset(train_idx))
        train, test = data.subset(train_idx), data.subset(test_idx)
        y_train = fold_targets(result, data, train_idx)
        y_test = fold_targets(result, data, test_idx)
        x_train, x_test = features(train.q, train.temperature), features(test.q, test.temperature)
        heads = [head for head in make_heads() if head.name in active]
        arrays = tuple(t.cpu().numpy() for t in (x_train, y_train, x_test))
        predictions = side_by_side(fit_and_predict, [(head, *arrays, seed, str(x_test.device)) for head in heads], jobs)
        for head, predicted in zip(heads, predictions):
            predicted_mm = torch.from_numpy(predicted).to(y_test.device)
            errors[head.name][test_idx] = (y_test - predicted_mm).norm(dim=-1).cpu().numpy()
        done = np.flatnonzero(np.isin(folds.fold, np.arange(f + 1)))
        if FUTILITY_AFTER_FOLDS <= f + 1 < folds.k:
            base = float(np.sqrt(np.mean(np.square(parent_errors[done]))))
            for name in list(active):
                rms = float(np.sqrt(np.mean(np.square(errors[name][done]))))
                if rms > (1.0 - margin / 2) * base:
                    active.remove(name)
                    out.stopped[name] = (f"stopped after {f + 1} of {folds.k} folds: held-out RMS {rms:.4f} mm "
                                         f"vs {base:.4f} mm without it on those poses (gain below {100 * margin / 2:g} %)")
    for name in names:
        if name not in out.stopped:
            out.candidates.append(Candidate(f"{parent}+{name}", errors[name], parent=parent, min_gain=margin,
                                             head=name))
    return out
