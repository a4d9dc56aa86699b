"""Validation on the public real-robot measurements (``../shared/data/real``), read in place.

Each set has protocols: a source split; grouped 5-fold cross-validation over configuration
regions (:mod:`torchcal.data.folds`); a seeded hold-out; fit on one measurement series
and score others after re-registering the tracker frame (the transfer protocols, the honest
ones: another day, another tracker placement); or the source's in-sample scoring. Every split
goes through the same steps as ``torchcal fit`` / ``torchcal evaluate``
(the one fit pipeline :func:`torchcal.stages.pipeline.fit_model`, :func:`~torchcal.stages.store.load_model`,
:func:`~torchcal.stages.geometry.held_out_errors`), with
a model folder in a temporary directory. Stages, each scored on poses the fit did not see:

* ``nominal (registered)``: the nominal model, instrument frame and tool fitted on the training
  poses (the frame re-registered on the scored poses where the protocol re-registers);
* ``geometry only``: geometric calibration (no joint-space terms, no head);
* ``default fit``: what ``torchcal fit`` does with no options: the structure (joint-space terms)
  and residual head chosen by the fit's own grouped cross-validation on its training poses.

Uncertainty check (:mod:`torchcal.stages.prediction_uncertainty`): for each method the share of
scored points inside their predicted 95 % region (the ball whose radius is the pose's predicted
95th percentile of the 3-D error) and the predicted against the observed 95th percentile of the
scored set.
"""

from __future__ import annotations

import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchcal.config.schema import FitConfig
from torchcal.core.errors import IdentifiabilityWarning
from torchcal.core.metrics import position_metrics
from torchcal.data.folds import make_folds
from torchcal.data.measurements import Measurements, load_measurements
from torchcal.identify.compliance import POINT_SETS
from torchcal.identify.joint_fit import option_label
from torchcal.kinematics.robot import load_robot
from torchcal.kinematics.transforms import rigid_registration
from torchcal.stages.geometry import held_out_errors, nominal_fit
from torchcal.stages.pipeline import fit_model
from torchcal.stages.prediction_uncertainty import LEVEL, METHODS, stored_prediction, subsample
from torchcal.stages.store import load_model

STAGES = ("nominal (registered)", "geometry only", "default fit")


@dataclass(frozen=True)
class Protocol:
    """One block of the validation table.

    ``fit_rows``: fit on this many rows of ``fit_file`` picked by numpy ``default_rng(0)``'s
    permutation (kept in file order). ``holdout``: score the rest of that permutation (the last
    ``round(holdout * n)`` rows) instead of ``test_files``. ``test_files``: scored with the same
    fit, each re-registered when ``register_test``. None of these: grouped K-fold CV.
    """

    dataset: str
    label: str
    fit_file: str
    test_files: tuple[str, ...] = ()
    folds: int = 5
    register_test: bool = False
    in_sample_first: int | None = None  # fit on all, score on the first k (source's in-sample protocol)
    fit_rows: int | None = None
    holdout: float | None = None
    published: str = ""
    slug_name: str = ""

    @property
    def slug(self) -> str:
        if self.slug_name:
            return f"{self.dataset}_{self.slug_name}"
        kind = ("insample" if self.in_sample_first else "holdout" if self.holdout else
                "register" if self.register_test else "split" if self.test_files else "cv")
        return f"{self.dataset}_{kind}"


UR10 = "ipa-ur10-tmac"
PROTOCOLS: tuple[Protocol, ...] = (
    Protocol("jacobi-ur5-gts3800", "source split: fit 1000 grid poses, score the 20 random test poses", "poses.csv",
             ("poses_test.csv",), published="mean 2.5664 -> 0.1549 mm (hybrid MDH + ASTGCN, test set)"),
    Protocol("jacobi-wam-gts3800", "source split: fit 216 grid poses, score the 20 random test poses (same base frame)",
             "poses_7dof.csv", ("poses_7dof_test.csv",), published="mean 17.7661 -> 2.9178 mm (hybrid, test set)"),
    Protocol(UR10, "series C (random poses): seeded 80/20 hold-out (2218 -> 555)", "poses_C_random.csv",
             holdout=0.2, published="none found"),
    Protocol(UR10, "TRANSFER: fit 3000 seeded rows of series A (grid), score all of C, then all of D, each "
             "re-registered", "poses_A_grid.csv", ("poses_C_random.csv", "poses_D_iso.csv"), register_test=True,
             fit_rows=3000, published="none found", slug_name="A_to_CD"),
    Protocol(UR10, "TRANSFER: fit all of series C, score series B re-registered", "poses_C_random.csv",
             ("poses_B_joint.csv",), register_test=True, published="none found", slug_name="C_to_B"),
    Protocol(UR10, "TRANSFER: fit all of series B, score series C re-registered", "poses_B_joint.csv",
             ("poses_C_random.csv",), register_test=True, published="none found", slug_name="B_to_C"),
    Protocol("icelinker-irb120-faro", "grouped 5-fold CV (982 poses, SMR 1)", "poses.csv", published="none"),
    Protocol("lmpytorch-rokae487-30", "grouped 5-fold CV (30 poses)", "poses.csv", published="none held out"),
    Protocol("lmpytorch-rokae487-30", "IN-SAMPLE: fit all 30, score the first 10 (the source's protocol)", "poses.csv",
             in_sample_first=10, published="mean 5.548 -> 0.167 mm (in-sample)"),
    Protocol("lmpytorch-rokae285-50", "grouped 5-fold CV (50 poses)", "poses.csv", published="none found"),
    Protocol("lmpytorch-rokae285-50", "IN-SAMPLE: fit all 50, score all (the source's code scores its fit poses)",
             "poses.csv", in_sample_first=50, published="none found"),
    Protocol("lmpytorch-rokae380-30", "grouped 5-fold CV (30 poses)", "poses.csv", published="none found"),
    Protocol("lmpytorch-rokae380-30", "IN-SAMPLE: fit all 30, score all (the source's code scores its fit poses)",
             "poses.csv", in_sample_first=30, published="none found"),
)


@dataclass
class StageErrors:
    errors: list[torch.Tensor] = field(default_factory=list)
    inside: dict[str, list[torch.Tensor]] = field(default_factory=dict)
    pooled: dict[str, list[torch.Tensor]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def _pairs(data: Measurements, protocol: Protocol, robot, folder: Path, seed: int) -> list[tuple[Measurements, list]]:
    """``(training poses, [scored poses, ...])`` of every split of ``protocol``."""
    n = len(data)
    if protocol.in_sample_first is not None:
        return [(data, [data.subset(np.arange(protocol.in_sample_first))])]
    if protocol.fit_rows is not None or protocol.holdout is not None:
        perm = np.random.default_rng(0).permutation(n)
        if protocol.fit_rows is not None:
            n_fit = protocol.fit_rows
        else:
            assert protocol.holdout is not None  # one of the two, by the test above
            n_fit = n - round(protocol.holdout * n)
        train = data.subset(np.sort(perm[:n_fit]))
        if protocol.holdout is not None:
            return [(train, [data.subset(np.sort(perm[n_fit:]))])]
        data = train
    if protocol.test_files:
        return [(data, [load_measurements(folder / f, robot) for f in protocol.test_files])]
    folds = make_folds("grouped", robot, data.q, k=protocol.folds, seed=seed)
    return [(data.subset(tr), [data.subset(te)]) for tr, te in folds.splits()]


def _nominal_errors(robot, train: Measurements, test: Measurements, register_test: bool) -> torch.Tensor:
    """The nominal robot with the instrument frame and the tool fitted on the training poses (what a
    user would call "nominal"); the frame alone re-registered on the scored poses where the protocol
    re-registers, as for the calibrated stages."""
    from dataclasses import replace

    _, t, tool = nominal_fit(robot, train)
    fitted = replace(robot, tool=tool)
    if register_test:
        t = rigid_registration(fitted.tcp_position(test.q), test.position)
    aligned = fitted.tcp_position(test.q) @ t[:3, :3].T + t[:3, 3]
    return test.position - aligned


def _predictions(stored, test: Measurements, errors: torch.Tensor) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Per method: whether each scored point is inside its predicted 95 % region, and the set's draws."""
    out = {}
    observed = errors.norm(dim=-1) * 1e3
    for method in METHODS:
        prediction = stored_prediction(stored, test.q, method)
        if prediction is not None:
            out[method] = (observed <= prediction.p95_mm, prediction.pooled_mm)
    return out


def _fit_and_score(robot, train: Measurements, tests: list[Measurements], protocol: Protocol, config,
                   folder: Path) -> dict:
    """One split through the fit pipeline -> load -> held-out errors of every scored set."""
    fitted = fit_model(folder, robot, train, config)
    result = fitted.result
    stored = load_model(folder)
    errors = [held_out_errors(stored, test, register=protocol.register_test) for test in tests]
    inside = [_predictions(stored, test, e) for test, e in zip(tests, errors)]
    structure_note = next((n for n in result.notes if n.startswith("structure chosen")), "")
    return {"result": result, "errors": errors, "inside": inside, "residual": fitted.residual,
            "structure_note": structure_note}


def _structure_name(result) -> str:
    points = tuple(result.compliance.points) if result.compliance is not None else ()
    gravity = next(name for name, members in POINT_SETS.items() if members == points)
    return option_label(gravity, result.harmonics.set_name if result.harmonics is not None else "none")


def run_protocol(root: Path, protocol: Protocol, *, residual: bool = True, seed: int = 0) -> dict:
    """Score one protocol; returns metrics per stage and scored set, coverage, choices and per-pose errors."""
    folder = root / protocol.dataset
    robot = load_robot(folder / "robot.yaml")
    data = load_measurements(folder / protocol.fit_file, robot)
    pairs = _pairs(data, protocol, robot, folder, seed)
    in_sample = protocol.in_sample_first is not None
    n_sets = len(pairs[0][1])
    stages = {(name, k): StageErrors() for name in STAGES for k in range(n_sets)}
    choices: list[str] = []
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        for i, (train, tests) in enumerate(pairs):
            for k, test in enumerate(tests):
                stages[("nominal (registered)", k)].errors.append(_nominal_errors(robot, train, test, protocol.register_test))
            runs = {"geometry only": FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none",
                                               seed=seed, progress=False),
                    "default fit": FitConfig(residual="none" if in_sample or not residual else "auto", seed=seed,
                                             progress=False)}
            for name, config in runs.items():
                out = _fit_and_score(robot, train, tests, protocol, config, Path(tmp) / f"{name[0]}{i}")
                for k in range(n_sets):
                    stages[(name, k)].errors.append(out["errors"][k])
                    for method, (inside, pooled) in out["inside"][k].items():
                        stages[(name, k)].inside.setdefault(method, []).append(inside)
                        stages[(name, k)].pooled.setdefault(method, []).append(pooled)
                if name == "default fit":
                    outcome = out["residual"]
                    head = outcome.kept if outcome is not None else None
                    choices.append(_structure_name(out["result"]) + (f" + {head}" if head else ""))
                    stages[(name, 0)].notes.append(out["structure_note"])
                    if outcome is not None:
                        stages[(name, 0)].notes.append(outcome.decision)
    labels = list(protocol.test_files) if protocol.test_files else ["held out" if not in_sample else "in-sample"]
    out = {"dataset": protocol.dataset, "protocol": protocol.label, "slug": protocol.slug,
           "published": protocol.published, "in_sample": in_sample, "n_splits": len(pairs), "scored_sets": labels,
           "stages": {}, "per_pose_mm": {}, "choices": choices}
    for (name, k), stage in stages.items():
        key = name if n_sets == 1 else f"{name} | {labels[k]}"
        errors = torch.cat(stage.errors)
        metrics: dict[str, Any] = position_metrics(errors)
        if stage.inside:
            metrics["uncertainty"] = {
                method: {"coverage_95": float(torch.cat(stage.inside[method]).double().mean()),
                         "predicted_p95_mm": float(torch.quantile(subsample(torch.cat(stage.pooled[method])), LEVEL)),
                         "observed_p95_mm": metrics["position_p95_mm"]}
                for method in stage.inside}
        if name == "default fit":
            metrics["status"] = "chosen per split: " + ", ".join(choices) + (" (in-sample: no head)" if in_sample else "")
            metrics["selection_notes"] = stages[(name, 0)].notes
        out["stages"][key] = metrics
        out["per_pose_mm"][key] = (errors.norm(dim=-1) * 1e3).tolist()
    return out
