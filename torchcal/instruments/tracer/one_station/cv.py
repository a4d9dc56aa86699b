"""Cross-validation of length-station structures: random rows against order-blocked folds.

A draw-wire's residuals drift in recording order (temperature, cable creep), so a random row
split scores a model on rows whose neighbours in time it was fitted on; contiguous blocks of
the file's order (:func:`torchcal.data.folds.block_folds`) score it on a stretch of
the recording it has not seen. The default structure is chosen on the blocked folds: the
simplest whose held-out RMS is within 1 % of the lowest (``nominal`` is a candidate, so the
choice is never worse than the nominal robot on those folds).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from torchcal.data.folds import make_folds
from torchcal.instruments.tracer.data import TracerData
from torchcal.instruments.tracer.one_station.fit import STRUCTURES, fit_station
from torchcal.kinematics.robot import RobotModel


def held_out_rms_mm(robot: RobotModel, data: TracerData, structure: str, split: str, *, k: int = 5,
                    seed: int = 0, **fit_options) -> float:
    """Pooled held-out length RMS (mm) of ``structure`` over ``k`` folds of kind ``split``.

    Each fold's model keeps the anchor, offset and attachment fitted on the other folds (the same
    physical set-up), so the score is the length prediction error on unseen rows.
    """
    folds = make_folds(split, robot, data.q, k=k, seed=seed, order=np.arange(len(data)))
    errors = []
    for train, test in folds.splits():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit = fit_station(robot, data.subset(torch.as_tensor(train)), structure, **fit_options)
        test_idx = torch.as_tensor(test)
        errors.append(fit.predict(data.q[test_idx]) - data.lengths[test_idx, 0])
    return float(torch.cat(errors).pow(2).mean().sqrt()) * 1e3


def compare_structures(robot: RobotModel, data: TracerData, *, k: int = 5, seed: int = 0,
                       structures: tuple[str, ...] = STRUCTURES, **fit_options) -> dict:
    """Held-out RMS of every structure under ``random`` and ``blocks`` folds, and the blocked choice."""
    rows: list[dict[str, float | str]] = [{"structure": name,
             "random_cv_rms_mm": held_out_rms_mm(robot, data, name, "random", k=k, seed=seed, **fit_options),
             "blocks_cv_rms_mm": held_out_rms_mm(robot, data, name, "blocks", k=k, seed=seed, **fit_options)}
            for name in structures]
    blocked = [float(r["blocks_cv_rms_mm"]) for r in rows]
    best = min(blocked)
    chosen = next(r["structure"] for r, score in zip(rows, blocked) if score <= 1.01 * best)
    return {"k": k, "rows": rows, "chosen": chosen,
            "rule": f"simplest structure within 1 % of the lowest {k}-fold order-blocked CV RMS"}
