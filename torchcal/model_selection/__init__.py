"""Model selection by evidence that transfers to new poses.

Every data-driven choice of a fit (keeping a residual head, joint-space error terms, the
stiffness parameterization, LASSO's penalty) is scored by cross-validation over folds from
:mod:`~torchcal.data.folds`: grouped by configuration (near-twin poses in one fold)
or contiguous blocks of measurement order; a random row split exists but is never the default.
:mod:`~torchcal.model_selection.compare` turns per-pose held-out errors of candidate models
into a decision (the simplest candidate within noise of the best) and a printable table;
:mod:`~torchcal.model_selection.leakage` says how close scored poses sit to the training poses.
"""

from torchcal.data.folds import SPLITS, Folds, make_folds, pose_embedding
from torchcal.model_selection.compare import Candidate, Comparison, compare_candidates
from torchcal.model_selection.leakage import LeakageReport, leakage_report

__all__ = [
    "SPLITS",
    "Candidate",
    "Comparison",
    "Folds",
    "LeakageReport",
    "compare_candidates",
    "leakage_report",
    "make_folds",
    "pose_embedding",
]
