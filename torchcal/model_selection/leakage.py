"""How close the scored poses sit to the poses a model was fitted on.

A test error says something about new poses only if the test poses are as far from the
training poses as new poses would be. Distances are tool-point displacements (m) in the
lever-arm-weighted joint space of :func:`~torchcal.data.folds.pose_embedding`, with
the training poses' lever arms. Two references:

* ``training_spacing``: each training pose's distance to its nearest *other* training pose, what
  a new pose drawn like the training poses would see;
* ``twin_share``: share of scored poses with a training pose within ``twin_radius_mm``, i.e.
  the same configuration up to a joint that hardly moves the tool point.

A warning is raised when the scored poses are near-twins of training poses
(``twin_share > 0.1``) or sit much closer to them than the training poses sit to each other
(median below half of the ``training_spacing`` median: test poses interleaved in a sweep).
"""

from __future__ import annotations

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

    def to_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        text = (f"distance to the nearest training pose (median tool-point motion): scored {self.scored_to_training_median_mm:.1f} mm, "
                f"training poses to each other {self.training_spacing_median_mm:.1f} mm; "
                f"{100 * self.twin_share:.0f} % of scored poses have a training twin within {self.twin_radius_mm:g} mm")
        return text + (f". WARNING: {self.warning}" if self.warning else "")


def _nearest(train: np.ndarray, query: np.ndarray, *, exclude_self: bool = False) -> np.ndarray:
    """Euclidean distance of each ``query`` row to its nearest ``train`` row (the nearest other one with
    ``exclude_self``, ``query`` being ``train``)."""
    # scipy's tree: a report imports it anyway (ISO 9283 repeats); sklearn's import takes 4x as long
    from scipy.spatial import cKDTree

    if exclude_self:
        return cKDTree(train).query(query, k=2)[0][:, -1]
    return cKDTree(train).query(query, k=1)[0]


def leakage_report(robot, train_q: torch.Tensor, scored_q: torch.Tensor, *, twin_radius_mm: float = 2.0) -> LeakageReport:
    """Compare scored poses' distance to the training poses with the references above (joints in rad)."""
    arms = joint_lever_arms(robot, train_q)
    train = pose_embedding(robot, train_q, arms)
    scored = pose_embedding(robot, scored_q, arms)
    d_scored = _nearest(train, scored) * 1e3
    d_train = _nearest(train, train, exclude_self=True) * 1e3 if len(train) > 1 else np.array([np.nan])
    twin_share = float(np.mean(d_scored < twin_radius_mm))
    report = LeakageReport(len(scored), len(train), float(np.median(d_scored)), float(np.median(d_train)),
                           twin_share, twin_radius_mm)
    reasons = []
    if twin_share > 0.1:
        reasons.append(f"{100 * twin_share:.0f} % of the scored poses repeat a training configuration")
    if report.scored_to_training_median_mm < 0.5 * report.training_spacing_median_mm:
        reasons.append("the scored poses sit closer to the training poses than those sit to each other")
    if reasons:
        report.warning = ("; ".join(reasons) + ": this error says little about new poses; score a different "
                          "measurement series or use grouped folds")
    return report
