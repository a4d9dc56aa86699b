"""What ``torchcal fit`` on tracker points says last, and what its report carries, with a kept residual head."""

from __future__ import annotations

import re
from dataclasses import replace

import pytest
import torch

from torchcal.config.schema import FitConfig
from torchcal.core.metrics import position_metrics
from torchcal.data.measurements import load_measurements, write_measurements_csv
from torchcal.instruments.tracker.plugin import _write_fit_report
from torchcal.model_selection.heads import make_features
from torchcal.residual import HEADS
from torchcal.residual.selection import fit_before_gate
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit, held_out_errors, model_joints, nominal_fit, save_fit
from torchcal.stages.residual import residual_targets_mm
from torchcal.stages.residual_store import StoredResidual, save_residual
from torchcal.stages.store import load_model


@pytest.fixture(scope="module")
def with_head(tmp_path_factory):
    """A geometry fit of a twin with gear errors, and an ELM head fitted on what it leaves, as ``fit`` stores a kept head."""
    root = tmp_path_factory.mktemp("head")
    twin = Twin.create(TwinConfig(seed=9, gear=True))
    sample = twin.sample(200, torch.Generator().manual_seed(4))
    write_measurements_csv(root / "train.csv", sample.q, sample.position)
    data = load_measurements(root / "train.csv", twin.robot)
    config = FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none", progress=False)
    folder = save_fit(root / "model", twin.robot, data, fit(twin.robot, data, config), {})
    stored = load_model(folder)
    head = HEADS["elm"](hidden=64, seed=0)
    features = make_features(stored.robot, data)
    targets = residual_targets_mm(stored.model, stored.x, data, model_joints(stored, data.q))
    fit_before_gate(head, features(data.q, None), targets, seed=0)
    save_residual(folder, StoredResidual(head, features, {"decision": "kept for the test"}))
    return folder, data, config


def test_last_line_gives_the_delivered_model_not_the_geometry(with_head):
    folder, data, config = with_head
    line = _write_fit_report(folder, data, None, [], config)
    stored = load_model(folder)
    full = position_metrics(held_out_errors(stored, data))["position_rms_mm"]
    geometry = position_metrics(held_out_errors(stored, data, residual=False))["position_rms_mm"]
    assert full < 0.9 * geometry  # the head learned something: the two figures differ
    assert "geometry + elm residual head" in line and "set by the options" in line
    figures = [float(v) for v in re.findall(r"(\d+\.\d{4}) mm \(", line)]
    assert figures[-1] == pytest.approx(full, abs=1e-4) and figures[-2] == pytest.approx(geometry, abs=1e-4)
    assert "(geometric)" not in line


def test_report_scores_each_stage_of_the_folder(with_head):
    folder, data, config = with_head
    _write_fit_report(folder, data, None, [], config)
    md = (folder / "report.md").read_text()
    stages = [row.split(" | ")[1] for row in md.splitlines() if row.startswith("| training file train")]
    assert stages[:3] == ["nominal", "geometry", "geometry + elm residual head"]
    assert "set by the options" in md and "elm residual head" in md


def test_evaluate_report_reuses_the_evaluation_instead_of_scoring_again(with_head, monkeypatch):
    from torchcal.instruments.tracker import evaluate, report
    from torchcal.kinematics import transforms as tf

    folder, data, _ = with_head
    stored = load_model(folder)
    flange = stored.model.instrument_from_base(stored.x) @ stored.model.base_flange_pose(data.q, stored.x)
    probe = tf.so3_exp(torch.tensor([0.01, -0.02, 0.3], dtype=torch.float64))
    oriented = replace(data, rotation=flange[..., :3, :3] @ probe)
    fits = []

    def counted(*args, **kwargs):
        fits.append(1)
        return nominal_fit(*args, **kwargs)

    monkeypatch.setattr(evaluate, "nominal_fit", counted)
    monkeypatch.setattr(report, "nominal_fit", counted)
    scored = evaluate.score(stored, oriented, register=True, corrections=False)
    fresh = report.score_pose_set(stored, oriented, held_out=True, register=True)
    assert len(fits) == 2
    reused = report.score_pose_set(stored, oriented, held_out=True, register=True, scored=scored)
    assert len(fits) == 2  # the report took the evaluation's nominal fit
    assert [s.name for s in reused.stages] == [s.name for s in fresh.stages]
    for a, b in zip(fresh.stages, reused.stages, strict=True):
        torch.testing.assert_close(a.errors_m, b.errors_m, rtol=0, atol=1e-15)
    for (name_a, a), (name_b, b) in zip(fresh.orientation, reused.orientation, strict=True):
        assert name_a == name_b and a.protocol == b.protocol
        torch.testing.assert_close(a.angles_rad, b.angles_rad, rtol=0, atol=1e-15)
