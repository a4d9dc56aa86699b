"""How close the scored poses sit to the poses a model was fitted on.

A test error says something about new poses only if the test poses are as far from the
training poses as new poses would be. Distances are tool-point displacements (m) in the
lever-arm-weighted joint space of :func:`~torchcal.data.folds.pose_embedding`, with
the training poses' lever arms. Two references:

* ``training_spacing``: each training pose's distance to its nearest *other* training pose, what
  a new pose drawn like the training poses would see;
* ``twin_share``: share of scored poses with a training pose within ``twin_radius_mm``, i.e.
  the same configuration up to a joint that hardly moves the tool point.

* ``far_share``: share of scored poses further than ``far_radius_mm`` from every training pose:
  further than a grouped cross-validation of the training poses holds a pose out from the poses
  it is predicted from (a reference grouped 5-fold split: the 95th percentile, over the training
  poses, of the distance to the nearest training pose of another fold, at least
  :data:`FAR_FLOOR_MM`; :func:`validated_radius_mm`). There the model extrapolates, which a
  cross-validation inside the measured region cannot see. No radius (NaN, nothing called far)
  where the poses cannot be split so (a handful of configurations).

A warning is raised when the scored poses are near-twins of training poses
(``twin_share > 0.1``), sit much closer to them than the training poses sit to each other
(median below half of the ``training_spacing`` median: test poses interleaved in a sweep), or
lie far from all of them (``far_share > 0.1``: the error there is extrapolation, and the predicted
95 % regions, calibrated on poses like the training poses, promise nothing).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch

from torchcal.data.folds import joint_lever_arms, pose_embedding


@dataclass
class LeakageReport:
    """Medians in mm of tool-point displacement; ``warning`` empty when the test set is fair."""

    n_scored: int
    n_training: int
    scored_to_training_median_mm: float
    training_spacing_median_mm: float
    twin_share: float
    twin_radius_mm: float
    warning: str = ""
    far_share: float = 0.0
    far_radius_mm: float = float("nan")

    def __post_init__(self) -> None:
        if self.far_radius_mm is None:  # as to_dict writes "none"
            self.far_radius_mm = float("nan")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["far_radius_mm"] = self.far_radius_mm if math.isfinite(self.far_radius_mm) else None  # strict JSON
        return d

    def summary(self) -> str:
        text = (f"distance to the nearest training pose (median tool-point motion): scored {self.scored_to_training_median_mm:.1f} mm, "
                f"training poses to each other {self.training_spacing_median_mm:.1f} mm; "
                f"{100 * self.twin_share:.0f} % of scored poses have a training twin within {self.twin_radius_mm:g} mm"
                + (f", {100 * self.far_share:.0f} % none within {self.far_radius_mm:.0f} mm"
                   if math.isfinite(self.far_radius_mm) else ""))
        return text + (f". WARNING: {self.warning}" if self.warning else "")


def _nearest(train: np.ndarray, query: np.ndarray, *, exclude_self: bool = False) -> np.ndarray:
    """Euclidean distance of each ``query`` row to its nearest ``train`` row (the nearest other one with
    ``exclude_self``, ``query`` being ``train``)."""
    # scipy's tree: a report imports it anyway (ISO 9283 repeats); sklearn's import takes 4x as long
    from scipy.spatial import cKDTree

    if exclude_self:
        return cKDTree(train).query(query, k=2)[0][:, -1]
    return cKDTree(train).query(query, k=1)[0]


#: Folds of the reference split (the fit's default count).
REFERENCE_FOLDS = 5
#: The far radius is never below this (mm): five times the twin radius, so that a dense sweep's
#: poses are not called far from their neighbours.
FAR_FLOOR_MM = 10.0


def validated_radius_mm(robot, train_q: torch.Tensor, train: np.ndarray) -> float:
    """How far a grouped cross-validation of ``train_q`` holds poses out: the 95th percentile, over
    the training poses, of the distance (mm, in the embedding ``train`` of ``train_q``) to the
    nearest training pose of another fold of a reference grouped split (at least
    :data:`FAR_FLOOR_MM`); NaN where the poses cannot be split so."""
    from torchcal.core.errors import DataError
    from torchcal.data.folds import grouped_folds

    if len(train_q) < 2 * REFERENCE_FOLDS:
        return float("nan")
    try:
        fold = grouped_folds(robot, train_q, k=REFERENCE_FOLDS).fold
    except (DataError, ValueError):  # too few distinct configurations for the groups
        return float("nan")
    reach = np.empty(len(train))
    for f in np.unique(fold):
        held = fold == f
        reach[held] = _nearest(train[~held], train[held])
    return max(float(np.percentile(reach, 95)) * 1e3, FAR_FLOOR_MM)


def distances(robot, train_q: torch.Tensor, scored_q: torch.Tensor) -> tuple[np.ndarray, np.ndarray, float]:
    """Scored pose to nearest training pose, training pose to nearest other (mm of tool-point motion),
    and the far radius (mm, :func:`validated_radius_mm`; NaN: none)."""
    arms = joint_lever_arms(robot, train_q)
    train = pose_embedding(robot, train_q, arms)
    scored = pose_embedding(robot, scored_q, arms)
    d_scored = _nearest(train, scored) * 1e3
    d_train = _nearest(train, train, exclude_self=True) * 1e3 if len(train) > 1 else np.array([np.nan])
    return d_scored, d_train, validated_radius_mm(robot, train_q, train)


def far_mask(d_scored: np.ndarray, radius: float) -> np.ndarray:
    """``(B,)`` whether each scored pose (its distance to the nearest training pose, mm) lies beyond the
    far ``radius`` (mm; NaN: no radius, none is far)."""
    return d_scored > radius if np.isfinite(radius) else np.zeros(len(d_scored), bool)


def far_from_training(robot, train_q: torch.Tensor, scored_q: torch.Tensor) -> tuple[np.ndarray, float]:
    """``(B,)`` whether each scored pose lies further than the far radius from every training pose, and that radius (mm)."""
    d_scored, _, radius = distances(robot, train_q, scored_q)
    return far_mask(d_scored, radius), radius


def leakage_report(robot, train_q: torch.Tensor, scored_q: torch.Tensor, *, twin_radius_mm: float = 2.0,
                   measured: tuple[np.ndarray, np.ndarray, float] | None = None) -> LeakageReport:
    """Compare scored poses' distance to the training poses with the references above (joints in rad);
    ``measured``: :func:`distances` of the same poses, where the caller has them."""
    d_scored, d_train, far_radius = distances(robot, train_q, scored_q) if measured is None else measured
    twin_share = float(np.mean(d_scored < twin_radius_mm))
    far_share = float(np.mean(far_mask(d_scored, far_radius))) if np.isfinite(far_radius) else 0.0
    report = LeakageReport(len(scored_q), len(train_q), float(np.median(d_scored)), float(np.median(d_train)),
                           twin_share, twin_radius_mm, far_share=far_share, far_radius_mm=far_radius)
    reasons = []
    if twin_share > 0.1:
        reasons.append(f"{100 * twin_share:.0f} % of the scored poses repeat a training configuration")
    if report.scored_to_training_median_mm < 0.5 * report.training_spacing_median_mm:
        reasons.append("the scored poses sit closer to the training poses than those sit to each other")
    if reasons:
        report.warning = ("; ".join(reasons) + ": this error says little about new poses; score a different "
                          "measurement series or use grouped folds")
    if far_share > 0.1:
        far = (f"{100 * far_share:.0f} % of the scored poses lie further than {far_radius:.0f} mm (tool-point motion) "
               "from every training pose, further than a grouped cross-validation of those poses holds any out: there "
               "the model extrapolates, which cross-validation inside the measured region cannot see, and the "
               "predicted 95 % regions promise nothing")
        report.warning = f"{report.warning}; {far}" if report.warning else far
    return report
