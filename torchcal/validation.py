"""Validation on the public real-robot measurements (``../shared/data/real``), read in place.

Each set has a protocol: a source split, K-fold cross-validation over poses, or fit on one
series and score another after re-registering the tracker frame. For every protocol and stage
(nominal after a rigid registration, geometric calibration, geometry + learned residual when it
wins on validation) the 3-D errors on poses the fit did not see are pooled and summarized. The
uncertainty check is the fraction of held-out points inside their predicted 95 % ellipsoid
(model covariance propagated to the point plus the fit's residual variance; the 3-D "2-sigma"
region: Mahalanobis distance^2 <= 7.81).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchcal.data.measurements import Measurements, load_measurements
from torchcal.errors import IdentifiabilityWarning
from torchcal.identify.calibrate import calibrate
from torchcal.kinematics.robot import load_robot
from torchcal.metrics import position_metrics
from torchcal.pipeline import registered_errors

CHI2_3_95 = 7.814727903251178


@dataclass(frozen=True)
class Protocol:
    """One row of the validation table."""

    dataset: str
    label: str
    fit_file: str
    test_file: str | None = None  # None: K-fold CV on fit_file
    folds: int = 5
    register_test: bool = False
    in_sample_first: int | None = None  # fit on all, score on the first k (source's in-sample protocol)
    published: str = ""


PROTOCOLS: tuple[Protocol, ...] = (
    Protocol("jacobi-ur5-gts3800", "source split (1000 grid -> 20 random)", "poses.csv", "poses_test.csv",
             published="mean 2.5664 -> 0.1549 mm (hybrid MDH + ASTGCN)"),
    Protocol("jacobi-wam-gts3800", "source split (216 grid -> 20)", "poses_7dof.csv", "poses_7dof_test.csv",
             published="mean 17.7661 -> 2.9178 mm (hybrid)"),
    Protocol("ipa-ur10-tmac", "series C, 5-fold CV", "poses_C_random.csv", published="not found"),
    Protocol("ipa-ur10-tmac", "fit C, test B (tracker frame re-registered)", "poses_C_random.csv", "poses_B_joint.csv",
             register_test=True, published="not found"),
    Protocol("icelinker-irb120-faro", "5-fold CV", "poses.csv", published="none"),
    Protocol("lmpytorch-rokae487-30", "5-fold CV", "poses.csv", published="(in-sample only, see next row)"),
    Protocol("lmpytorch-rokae487-30", "in-sample, first 10 of 30 (source protocol)", "poses.csv", in_sample_first=10,
             published="mean 5.548 -> 0.167 mm (in-sample)"),
)


@dataclass
class StageErrors:
    errors: list[torch.Tensor] = field(default_factory=list)
    inside: list[torch.Tensor] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def _predicted_inside_95(result, q: torch.Tensor, errors: torch.Tensor) -> torch.Tensor:
    """Whether each error lies in its predicted 95 % ellipsoid."""
    _, jac = result.model.position_jacobian(q, result.x, result.free)
    cov = torch.einsum("bip,pq,bjq->bij", jac, result.covariance, jac)
    cov = cov + (result.sigma_residual_m**2) * torch.eye(3, dtype=cov.dtype)
    d2 = torch.einsum("bi,bij,bj->b", errors, torch.linalg.inv(cov), errors)
    return d2 <= CHI2_3_95


def _splits(n: int, protocol: Protocol, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    if protocol.in_sample_first is not None:
        return [(np.arange(n), np.arange(protocol.in_sample_first))]
    rng = np.random.default_rng(seed)
    fold = rng.permutation(n) % protocol.folds
    return [(np.flatnonzero(fold != k), np.flatnonzero(fold == k)) for k in range(protocol.folds)]


def run_protocol(root: Path, protocol: Protocol, *, residual: bool = True, seed: int = 0) -> dict:
    """Score one protocol; returns metrics per stage plus coverage and notes."""
    folder = root / protocol.dataset
    robot = load_robot(folder / "robot.yaml")
    data = load_measurements(folder / protocol.fit_file, robot)
    if protocol.test_file is not None:
        test = load_measurements(folder / protocol.test_file, robot)
        pairs = [(data, test)]
    else:
        pairs = [(data.subset(tr), data.subset(te)) for tr, te in _splits(len(data), protocol, seed)]
    stages = {"nominal (registered)": StageErrors(), "geometric": StageErrors()}
    residual_stage = StageErrors()
    for train, test in pairs:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", IdentifiabilityWarning)
            result = calibrate(robot, train)
        # nominal: frame registered on the training poses (on the test poses when frames differ)
        if protocol.register_test:
            nominal = registered_errors(robot.tcp_position(test.q), test.position)
        else:
            frame_source = train
            from torchcal.kinematics.transforms import rigid_registration

            t = rigid_registration(robot.tcp_position(frame_source.q), frame_source.position)
            nominal = test.position - (robot.tcp_position(test.q) @ t[:3, :3].T + t[:3, 3])
        predicted = result.model.tcp_position(test.q, result.x)
        geometric = registered_errors(predicted, test.position) if protocol.register_test else test.position - predicted
        stages["nominal (registered)"].errors.append(nominal)
        stages["geometric"].errors.append(geometric)
        stages["geometric"].inside.append(_predicted_inside_95(result, test.q, geometric))
        if residual:
            from torchcal.residual_stage import residual_for_validation

            outcome = residual_for_validation(result, train, test, register_test=protocol.register_test, seed=seed)
            residual_stage.errors.append(outcome["errors"])
            residual_stage.notes.append(outcome["decision"])
    out = {
        "dataset": protocol.dataset,
        "protocol": protocol.label,
        "published": protocol.published,
        "stages": {},
    }
    for name, stage in stages.items():
        metrics = position_metrics(torch.cat(stage.errors))
        if stage.inside:
            metrics["inside_95_fraction"] = float(torch.cat(stage.inside).double().mean())
        out["stages"][name] = metrics
    if residual and residual_stage.errors:
        out["stages"]["geometric + residual"] = position_metrics(torch.cat(residual_stage.errors))
        out["residual_decisions"] = residual_stage.notes
    return out
