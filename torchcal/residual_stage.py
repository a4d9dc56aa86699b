"""The learned-residual stage of ``fit``: targets, split, candidate heads, gate, storage.

Targets are the training poses' position errors left by the geometric model, rotated into the
``base`` frame (so a head is independent of where the tracker stood) and scaled to mm. The
training poses are split once (seeded) into a part the heads are fitted on and a validation part
that decides: a head is kept only if it lowers the validation RMS by ``residual_margin``
compared with predicting zero; otherwise the model stays geometric and the run says so.
"""

from __future__ import annotations

import torch

from torchcal.data.measurements import Measurements
from torchcal.residual import HEADS
from torchcal.residual.features import JointFeatures
from torchcal.residual.selection import Selection, refit_on_all, select_head

AUTO_HEADS = ("mma-elm", "mlp")


def _candidates(config) -> list:
    names = AUTO_HEADS if config.residual == "auto" else tuple(n.strip() for n in config.residual.split("+"))
    heads = []
    for name in names:
        if name not in HEADS:
            from torchcal.errors import TorchcalError

            raise TorchcalError(f"unknown residual head '{name}'; choose auto, none or any of {sorted(HEADS)} (joined by +)")
        if name == "mma-elm":
            heads.append(HEADS[name](hidden=config.residual_hidden, population=config.mayfly_population,
                                     iterations=config.mayfly_iterations, seed=config.seed, progress=config.progress))
        elif name == "elm":
            heads.append(HEADS[name](hidden=config.residual_hidden, seed=config.seed))
        else:
            heads.append(HEADS[name](seed=config.seed, progress=config.progress))
    return heads


def residual_targets_mm(model, x, data: Measurements, joints: torch.Tensor | None = None) -> torch.Tensor:
    """Geometric residuals of ``data`` in the ``base`` frame, mm ``(n, 3)``.

    ``joints``: what the chain is evaluated at (default ``data.q``; ``q`` plus the joint-space
    errors when the model has any), while the head's features stay the commanded joints.
    """
    error = data.position - model.tcp_position(data.q if joints is None else joints, x)
    return error @ model.T_reference[:3, :3].to(error) * 1e3


def split(n: int, fraction: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    n_val = max(1, int(round(fraction * n)))
    return perm[n_val:], perm[:n_val]


def choose_residual(model, x, robot, data: Measurements, config, joints: torch.Tensor | None = None) -> tuple[Selection, JointFeatures]:
    temperature = None
    if data.temperature is not None:
        t = data.temperature
        temperature = (float(t.mean()), float(t.std().clamp_min(1e-6)))
    features = JointFeatures(robot.joint_limits.to(torch.float64), temperature)
    feats = features(data.q, data.temperature)
    targets = residual_targets_mm(model, x, data, joints)
    train, val = split(len(data), config.validation_fraction, config.seed)
    selection = select_head(_candidates(config), feats[train], targets[train], feats[val], targets[val], seed=config.seed,
                            margin=config.residual_margin)
    if selection.head is not None and getattr(config, "residual_refit", True):
        refit_on_all(selection.head, feats[train], targets[train], feats[val], targets[val], seed=config.seed)
        selection.decision += "; refitted on all training poses"
    return selection, features


def fit_residual_stage(model_dir, data: Measurements, config, console=None) -> dict:
    """Fit and gate the residual for a saved geometric model; writes the head when kept."""
    from torchcal.model_store import load_model
    from torchcal.residual_store import StoredResidual, save_residual

    from torchcal.pipeline import model_joints

    stored = load_model(model_dir)
    selection, features = choose_residual(stored.model, stored.x, stored.robot, data, config, model_joints(stored, data.q))
    summary = {"decision": selection.decision, "validation_rms_mm": selection.validation_rms,
               "geometric_validation_rms_mm": selection.baseline_rms, "kept": selection.head.name if selection.head else None}
    if selection.head is not None:
        save_residual(model_dir, StoredResidual(selection.head, features, {"decision": selection.decision,
                                                                           "validation_rms_mm": selection.validation_rms,
                                                                           "geometric_validation_rms_mm": selection.baseline_rms}))
    if console is not None:
        console.log(selection.decision)
    return summary


def residual_for_validation(result, train: Measurements, test: Measurements, *, register_test: bool, seed: int, config=None) -> dict:
    """Held-out errors of geometry + gated residual (geometry alone where the gate says no)."""
    from torchcal.pipeline import FitConfig, registered_errors

    from torchcal.identify.joint_errors import JointSpaceErrors
    from torchcal.identify.joint_fit import predicted_positions

    config = config or FitConfig(seed=seed)
    joint_errors = JointSpaceErrors.of(result)
    joints = None if joint_errors.empty else joint_errors.effective_joints(result.model.robot, train.q)
    selection, features = choose_residual(result.model, result.x, result.model.robot, train, config, joints)
    predicted = predicted_positions(result, test.q)
    if selection.head is not None:
        with torch.no_grad():
            base_err_mm = selection.head.predict(features(test.q, test.temperature))
        predicted = predicted + (base_err_mm * 1e-3) @ result.model.T_reference[:3, :3].T.to(predicted)
    errors = registered_errors(predicted, test.position) if register_test else test.position - predicted
    return {"errors": errors, "decision": selection.decision}
