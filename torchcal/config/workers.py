"""The worker processes a fit's options call for, started from the options alone.

Nothing here imports the numerical stack, so a command can start the workers first thing: their
start-up (torch and the fit's modules, about a second) then overlaps the command's own imports
instead of following them (:mod:`torchcal.core.workers`).
"""

from __future__ import annotations

from typing import Any

from torchcal.core.workers import resolve_jobs, warm_up

#: What the structure cross-validation's fold fits import.
STRUCTURE_MODULES = ("torchcal.model_selection.structure",)
#: What grouped folds import (k-means and the merging of near twins, :mod:`torchcal.data.folds`): a worker
#: makes them while this process chooses the prior.
GROUPED_FOLD_MODULES = ("sklearn.cluster", "sklearn.neighbors")


def cross_validates(config: Any) -> bool:
    """Whether a fit with the options ``config`` (a ``FitConfig``) compares anything on folds: residual
    heads, or joint-space options left to the data (``auto``: several structures to score)."""
    return config.residual != "none" or "auto" in (config.gravity_compliance, config.joint_harmonics)


def start_fit_workers(config: Any) -> None:
    """Start the worker processes of a fit with ``config`` in the background, importing what its folds
    and the structure cross-validation's fold fits need.

    Nothing to do with ``jobs=1``, nor for a fit that cross-validates nothing (geometry alone: its
    folds take a fraction of a second, less than a worker's start-up costs beside it:
    docs/benchmarks.md). A worker runs its queue in order, imports included: each later piece's
    imports are queued when the fit is about to need them
    (:func:`~torchcal.core.workers.import_in_workers`), so that they do not hold up the folds.
    """
    if not cross_validates(config):
        return
    groups = [STRUCTURE_MODULES] + ([GROUPED_FOLD_MODULES] if config.split == "grouped" else [])
    warm_up(min(resolve_jobs(config.jobs), max(config.cv_folds, 2)), *groups)
