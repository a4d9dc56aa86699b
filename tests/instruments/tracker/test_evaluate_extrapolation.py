"""``evaluate`` on poses far from every training pose says so: a leakage warning and the predicted
regions' coverage told apart for those poses (where the model extrapolates) and the others."""

from __future__ import annotations

import warnings

import numpy as np
import torch

from torchcal.config.schema import FitConfig
from torchcal.data.measurements import load_measurements, write_measurements_csv
from torchcal.instruments.tracker.evaluate import score
from torchcal.model_selection.leakage import far_from_training
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit_with_selection, save_fit
from torchcal.stages.store import load_model


def _measured(twin, q, path, generator):
    write_measurements_csv(path, q, twin.measure(q, generator))
    return load_measurements(path, twin.robot)


def test_poses_far_from_the_training_region_are_scored_apart(tmp_path):
    twin = Twin.create(TwinConfig(seed=2))
    gen = torch.Generator().manual_seed(4)
    limits = twin.robot.joint_limits
    corner = limits[:, 0] + (0.1 + 0.25 * torch.rand(150, twin.robot.dof, generator=gen, dtype=torch.float64)) * (limits[:, 1] - limits[:, 0])
    corner[:, 3:] = twin.robot.sample_joints(150, gen)[:, 3:]
    train = _measured(twin, corner, tmp_path / "train.csv", gen)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        config = FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none", progress=False)
        result, structure = fit_with_selection(twin.robot, train, config)
        stored = load_model(save_fit(tmp_path / "model", twin.robot, train, result, {}, structure=structure,
                                     uncertainty=config.uncertainty))
    everywhere = _measured(twin, twin.robot.sample_joints(200, gen, margin=0.1), tmp_path / "test.csv", gen)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scored = score(stored, everywhere, corrections=False)
    u, leakage = scored.metrics["uncertainty"], scored.metrics["leakage"]
    far, radius = far_from_training(twin.robot, stored.training_q, everywhere.q)
    assert u["n_far"] == int(far.sum()) > 0.3 * len(far) and u["far_radius_mm"] == radius == leakage["far_radius_mm"]
    assert "extrapolates" in leakage["warning"]
    inside = scored.errors.norm(dim=-1).numpy() * 1e3 <= np.asarray(u["per_pose_predicted_p95_mm"])
    assert u["coverage_95_far"] == float(inside[far].mean()) and u["coverage_95_like_training"] == float(inside[~far].mean())
    assert "5-fold CV over" in u["protocol"]  # the calibration's own protocol, as uncertainty.json states it
