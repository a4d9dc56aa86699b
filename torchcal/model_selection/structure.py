"""Cross-validation of a fit's structures: geometry alone, geometry with joint-space error terms.

For every fold (:mod:`~torchcal.data.folds`), geometry is identified once on the
training part and every joint-space option (gravity compliance, first harmonics) refines it
there; the held-out part scores each. The per-fold fits are kept: the residual-head stage
(:mod:`~torchcal.model_selection.heads`) learns on their residuals, so a head is judged on top
of exactly the structure that will carry it, with the same folds.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from functools import partial

import numpy as np
import torch

from torchcal.core.errors import IdentifiabilityWarning
from torchcal.core.threads import fit_threads
from torchcal.core.workers import side_by_side, started_workers
from torchcal.data.folds import Folds
from torchcal.data.measurements import Measurements
from torchcal.identify.calibrate import CalibrationResult
from torchcal.identify.compliance import POINT_SETS
from torchcal.identify.harmonics import HARMONIC_SETS
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.identify.joint_fit import fit_joint_errors, option_label, predicted_positions
from torchcal.identify.prior import PriorSpec
from torchcal.identify.series_frames import held_out_errors as series_held_out
from torchcal.model_selection.compare import Candidate, Comparison, compare_candidates


@dataclass
class StructureCV:
    """Folds, per-pose out-of-fold errors per option, the per-fold fits and the decision.

    Attributes:
        folds: the folds used.
        options: ``(gravity set, harmonic set)`` pairs, simplest first.
        candidates: one :class:`~torchcal.model_selection.compare.Candidate` per option.
        fold_results: ``label -> [result of fold 0, 1, ...]`` (fits on each training part).
        comparison: the decision among options.
        error_vectors_mm: ``label -> (n, 3)`` out-of-fold error vectors (instrument frame, mm),
            whose norms are the candidates' ``errors_mm``.
    """

    folds: Folds
    options: list[tuple[str, str]]
    candidates: list[Candidate]
    fold_results: dict[str, list]
    comparison: Comparison
    error_vectors_mm: dict[str, np.ndarray] = field(default_factory=dict)
    prior: PriorSpec | None = None  # the geometry's prior (identify.prior), for fits that must repeat it
    prior_start: CalibrationResult | None = None  # the MAP fit on all poses with that prior: later fits start from it

    @property
    def chosen(self) -> tuple[str, str]:
        return next(o for o in self.options if structure_label(*o) == self.comparison.chosen)


def structure_label(gravity: str, harmonics: str) -> str:
    """``geometry``, ``geometry+wrist``, ``geometry+harmonics``, ... (table names)."""
    option = option_label(gravity, harmonics)
    return "geometry" if option == "none" else f"geometry+{option}"


def cross_validate_structures(robot, data: Measurements, fit_geometry, options: list[tuple[str, str]], folds: Folds,
                              *, tolerance: float = 0.01, harmonic_min_range_deg: float = 0.0,
                              progress=None, jobs: int = 1) -> StructureCV:
    """Score every option on ``folds``; ``fit_geometry(train) -> CalibrationResult``.

    ``progress(step: str)``, if given, is called before the folds. ``jobs``: processes that fit the
    folds side by side (:func:`torchcal.core.workers.side_by_side`; the same fits as one by one).
    """
    n = len(data)
    vectors = {structure_label(*o): np.zeros((n, 3)) for o in options}
    fold_results: dict[str, list] = {structure_label(*o): [] for o in options}
    if progress is not None:
        progress(f"cross-validating structures on {folds.k} folds")
    splits = list(folds.splits())
    # With a worker, each fold's options go out in two halves (every other option: their costs alike):
    # k whole folds on two processes would leave one of them a fold more. A half repeats the fold's
    # geometry fit, a few steps from the warm start; each option's fit is the same as in one piece.
    halves = 2 if len(options) > 1 and started_workers(jobs) > 0 else 1
    chunks = [list(range(len(options)))[h::halves] for h in range(halves)]
    tasks = [(robot, data, train_idx, test_idx, fit_geometry, [options[i] for i in chunk], harmonic_min_range_deg)
             for train_idx, test_idx in splits for chunk in chunks]
    pieces = iter(side_by_side(fit_fold, tasks, jobs))
    for _train_idx, test_idx in splits:  # in fold order: fold_results[label][f] is fold f's fit
        for chunk in chunks:
            for i, (held_out_mm, result) in zip(chunk, next(pieces)):
                label = structure_label(*options[i])
                vectors[label][test_idx] = held_out_mm
                fold_results[label].append(result)
    candidates = [Candidate(label, np.linalg.norm(v, axis=1)) for label, v in vectors.items()]
    comparison = compare_candidates(candidates, folds.units(), folds.description, tolerance=tolerance)
    return StructureCV(folds, options, candidates, fold_results, comparison, vectors)


def fit_fold(robot, data: Measurements, train_idx: np.ndarray, test_idx: np.ndarray, fit_geometry,
             options: list[tuple[str, str]], harmonic_min_range_deg: float) -> list[tuple[np.ndarray, CalibrationResult]]:
    """One fold: geometry identified on the training part, every option refining it there; per option,
    the held-out error vectors (instrument frame, mm ``(k, 3)``) and the fit. A worker process can run it."""
    with warnings.catch_warnings(), fit_threads():
        # a fold's fit repeats the identifiability warnings of the full fit, which is reported once
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        train, test = data.subset(train_idx), data.subset(test_idx)
        geometry = fit_geometry(train)
        fits = []
        for gravity, harmonics in options:
            result = fit_joint_errors(robot, train, geometry, POINT_SETS[gravity], HARMONIC_SETS[harmonics],
                                      harmonic_min_range_deg)
            # pooled series: each later series in the frame the fold fit gives it (identify.series_frames)
            held_out = series_held_out(partial(predicted_positions, result), train, test)
            fits.append((held_out.detach().cpu().numpy() * 1e3, result))
    return fits


def fold_targets(result, data: Measurements, index: np.ndarray) -> torch.Tensor:
    """Errors (base frame, mm ``(k, 3)``) that ``result`` leaves at poses ``index`` of ``data``."""
    part = data.subset(index)
    joints = JointSpaceErrors.of(result).effective_joints(result.model.robot, part.q)
    error = part.position - result.model.tcp_position(joints, result.x)
    return error @ result.model.T_reference[:3, :3].to(error) * 1e3
