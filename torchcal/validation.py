"""Validation on the public real-robot measurements (``../shared/data/real``), read in place.

Each set has a protocol: a source split, K-fold cross-validation over poses, fit on one series
and score another after re-registering the tracker frame, or the source's in-sample scoring.
Every split goes through the same steps as ``torchcal fit`` / ``torchcal evaluate``
(:func:`torchcal.pipeline.fit`, :func:`~torchcal.pipeline.save_fit`, the gated residual stage,
:func:`~torchcal.model_store.load_model`, :func:`~torchcal.pipeline.held_out_errors`), with a
model folder in a temporary directory. Stages, each scored on poses the fit did not see:

* ``nominal (registered)``: the nominal model, instrument frame registered on the training poses
  (on the scored poses where the protocol re-registers);
* ``geometric``: geometric calibration;
* ``geometric + joint-space errors``: geometry with joint compliance under gravity and
  first-harmonic joint errors, which of them chosen by 5-fold CV on the training poses only
  (``gravity_compliance=auto``, ``joint_harmonics=auto``); where the CV chooses ``none`` this row
  equals the geometric one and says so;
* ``+ learned residual``: the gated head on top of the previous stage; where the gate keeps no
  head on the training poses this row repeats the previous one, marked "gated off".

Uncertainty check: the fraction of scored points inside their predicted 95 % ellipsoid (model
covariance propagated to the point plus the fit's residual variance, or the kept head's
validation variance; the 3-D "2-sigma" region: Mahalanobis distance^2 <= 7.81).
"""

from __future__ import annotations

import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchcal.data.measurements import Measurements, load_measurements
from torchcal.errors import IdentifiabilityWarning
from torchcal.identify.compliance import POINT_SETS
from torchcal.identify.joint_fit import option_label
from torchcal.kinematics.robot import load_robot
from torchcal.kinematics.transforms import rigid_registration
from torchcal.metrics import position_metrics

CHI2_3_95 = 7.814727903251178
STAGES = ("nominal (registered)", "geometric", "geometric + joint-space errors", "+ learned residual")


@dataclass(frozen=True)
class Protocol:
    """One block of the validation table."""

    dataset: str
    label: str
    fit_file: str
    test_file: str | None = None  # None: K-fold CV on fit_file
    folds: int = 5
    register_test: bool = False
    in_sample_first: int | None = None  # fit on all, score on the first k (source's in-sample protocol)
    published: str = ""

    @property
    def slug(self) -> str:
        kind = "insample" if self.in_sample_first else ("split" if self.test_file and not self.register_test else
                                                        "register" if self.register_test else "cv")
        return f"{self.dataset}_{kind}"


PROTOCOLS: tuple[Protocol, ...] = (
    Protocol("jacobi-ur5-gts3800", "source split: fit 1000 grid poses, score the 20 random test poses", "poses.csv",
             "poses_test.csv", published="mean 2.5664 -> 0.1549 mm (hybrid MDH + ASTGCN, test set)"),
    Protocol("jacobi-wam-gts3800", "source split: fit 216 grid poses, score the 20 random test poses (same base frame)",
             "poses_7dof.csv", "poses_7dof_test.csv", published="mean 17.7661 -> 2.9178 mm (hybrid, test set)"),
    Protocol("ipa-ur10-tmac", "series C (random poses), 5-fold CV", "poses_C_random.csv", published="none found"),
    Protocol("ipa-ur10-tmac", "fit all of series C, score series B after a rigid re-registration of B",
             "poses_C_random.csv", "poses_B_joint.csv", register_test=True, published="none found"),
    Protocol("icelinker-irb120-faro", "5-fold CV (982 poses, SMR 1)", "poses.csv", published="none"),
    Protocol("lmpytorch-rokae487-30", "5-fold CV (30 poses)", "poses.csv", published="none held out"),
    Protocol("lmpytorch-rokae487-30", "IN-SAMPLE: fit all 30, score the first 10 (the source's protocol)", "poses.csv",
             in_sample_first=10, published="mean 5.548 -> 0.167 mm (in-sample)"),
)


@dataclass
class StageErrors:
    errors: list[torch.Tensor] = field(default_factory=list)
    inside: list[torch.Tensor] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def inside_95(point_jacobian: torch.Tensor, cov: torch.Tensor, sigma_m: float, errors: torch.Tensor) -> torch.Tensor:
    """Whether each error ``(B, 3)`` lies in its predicted 95 % ellipsoid.

    ``point_jacobian (B, 3, K)`` and ``cov (K, K)`` give the model's prediction covariance;
    ``sigma_m`` is the per-coordinate scatter a single measurement adds around the model.
    """
    pred_cov = torch.einsum("bip,pq,bjq->bij", point_jacobian, cov, point_jacobian)
    pred_cov = pred_cov + (sigma_m**2) * torch.eye(3, dtype=pred_cov.dtype)
    d2 = torch.einsum("bi,bij,bj->b", errors, torch.linalg.inv(pred_cov), errors)
    return d2 <= CHI2_3_95


def _splits(n: int, protocol: Protocol, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    if protocol.in_sample_first is not None:
        return [(np.arange(n), np.arange(protocol.in_sample_first))]
    rng = np.random.default_rng(seed)
    fold = rng.permutation(n) % protocol.folds
    return [(np.flatnonzero(fold != k), np.flatnonzero(fold == k)) for k in range(protocol.folds)]


def _nominal_errors(robot, train: Measurements, test: Measurements, register_test: bool) -> torch.Tensor:
    source = test if register_test else train
    t = rigid_registration(robot.tcp_position(source.q), source.position)
    aligned = robot.tcp_position(test.q) @ t[:3, :3].T + t[:3, 3]
    return test.position - aligned


def _coverage(stored, test: Measurements, errors: torch.Tensor, sigma_m: float) -> torch.Tensor:
    from torchcal.pipeline import model_joints

    _, jac = stored.model.position_jacobian(model_joints(stored, test.q), stored.x, stored.free, method="analytic")
    return inside_95(jac, stored.covariance, sigma_m, errors)


def _choice_label(result) -> str:
    """The joint-space terms a fit kept, named as in the CV notes (:func:`option_label`)."""
    points = tuple(result.compliance.points) if result.compliance is not None else ()
    gravity = next(name for name, members in POINT_SETS.items() if members == points)
    return option_label(gravity, "first" if result.harmonics is not None else "none")


def _fit_and_score(robot, train: Measurements, test: Measurements, protocol: Protocol, config, folder: Path,
                   residual: bool) -> dict:
    """One split through fit -> save -> residual stage -> load -> held-out errors."""
    from torchcal.model_store import load_model
    from torchcal.pipeline import fit, held_out_errors, save_fit
    from torchcal.residual_stage import fit_residual_stage

    result = fit(robot, train, config)
    save_fit(folder, robot, train, result, {})
    summary = fit_residual_stage(folder, train, config) if residual else None
    stored = load_model(folder)
    geometric = held_out_errors(stored, test, register=protocol.register_test, residual=False)
    out = {"result": result, "errors": geometric,
           "inside": _coverage(stored, test, geometric, result.sigma_residual_m), "residual": summary}
    if stored.residual is not None:
        with_head = held_out_errors(stored, test, register=protocol.register_test)
        head_sigma = summary["validation_rms_mm"][summary["kept"]] * 1e-3 / 3**0.5
        out["head_errors"] = with_head
        out["head_inside"] = _coverage(stored, test, with_head, head_sigma)
    return out


def run_protocol(root: Path, protocol: Protocol, *, residual: bool = True, seed: int = 0) -> dict:
    """Score one protocol; returns metrics per stage plus coverage, choices and per-pose errors."""
    from torchcal.pipeline import FitConfig

    folder = root / protocol.dataset
    robot = load_robot(folder / "robot.yaml")
    data = load_measurements(folder / protocol.fit_file, robot)
    if protocol.test_file is not None:
        pairs = [(data, load_measurements(folder / protocol.test_file, robot))]
    else:
        pairs = [(data.subset(tr), data.subset(te)) for tr, te in _splits(len(data), protocol, seed)]
    in_sample = protocol.in_sample_first is not None
    stages = {name: StageErrors() for name in STAGES}
    choices: list[str] = []
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        for k, (train, test) in enumerate(pairs):
            stages["nominal (registered)"].errors.append(_nominal_errors(robot, train, test, protocol.register_test))
            geo = _fit_and_score(robot, train, test, protocol,
                                 FitConfig(residual="none", seed=seed, progress=False), Path(tmp) / f"g{k}", False)
            stages["geometric"].errors.append(geo["errors"])
            stages["geometric"].inside.append(geo["inside"])
            comp = _fit_and_score(robot, train, test, protocol,
                                  FitConfig(residual="none" if in_sample or not residual else "auto",
                                            gravity_compliance="auto", joint_harmonics="auto", seed=seed,
                                            progress=False),
                                  Path(tmp) / f"c{k}", residual and not in_sample)
            choices.append(_choice_label(comp["result"]))
            stages["geometric + joint-space errors"].errors.append(comp["errors"])
            stages["geometric + joint-space errors"].inside.append(comp["inside"])
            stages["geometric + joint-space errors"].notes += [n for n in comp["result"].notes if "chosen by" in n]
            head = stages["+ learned residual"]
            if comp["residual"] is not None:
                head.notes.append(comp["residual"]["decision"])
            head.errors.append(comp.get("head_errors", comp["errors"]))
            head.inside.append(comp.get("head_inside", comp["inside"]))
    out = {"dataset": protocol.dataset, "protocol": protocol.label, "slug": protocol.slug,
           "published": protocol.published, "in_sample": in_sample, "n_splits": len(pairs),
           "stages": {}, "per_pose_mm": {}, "compliance_choices": choices}
    for name, stage in stages.items():
        if name == "+ learned residual" and (in_sample or not residual):
            out["stages"][name] = {"status": "not scored (in-sample: a head reproduces its own training poses)"
                                   if in_sample else "not run"}
            continue
        errors = torch.cat(stage.errors)
        metrics = position_metrics(errors)
        if stage.inside:
            metrics["inside_95_fraction"] = float(torch.cat(stage.inside).double().mean())
        if name == "geometric + joint-space errors":
            metrics["status"] = "chosen per split: " + ", ".join(choices)
            metrics["cv_notes"] = stage.notes
        if name == "+ learned residual":
            kept = sum(d.startswith("residual head") for d in stage.notes)
            metrics["status"] = "gated off" if kept == 0 else f"head kept in {kept} of {len(stage.notes)} splits"
            metrics["gate_decisions"] = stage.notes
        out["stages"][name] = metrics
        out["per_pose_mm"][name] = (errors.norm(dim=-1) * 1e3).tolist()
    return out
