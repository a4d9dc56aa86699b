"""`torchcal run` with its export checked in a worker beside the report: the report waits for the
export's check and states what it found, and the run's summary carries it."""

from __future__ import annotations

import json

import pytest

from torchcal.config.schema import RunConfig
from torchcal.core.workers import ready_workers, warm_up
from torchcal.instruments.tracker.run import run
from torchcal.sim.twin import TwinConfig


@pytest.mark.slow
def test_export_beside_the_report_reaches_the_report_and_the_summary(tmp_path):
    out, exported = tmp_path / "runs", tmp_path / "exported"
    config = RunConfig(name="small", out=str(out), export_dir=str(exported),
                       twin=TwinConfig(seed=2, gravity=True, n_train=150, n_test=60))
    config.fit.residual, config.fit.gravity_compliance, config.fit.joint_harmonics = "none", "elbow+wrist", "none"
    config.fit.progress, config.fit.jobs = False, 2
    warm_up(2, ["torchcal.compensate.export"], wait=True)  # a worker ready when the export starts
    assert ready_workers() == 1
    summary = run(config)
    truth = summary["export"]["compensation_on_true_robot"]
    report = (out / "small" / "report.md").read_text(encoding="utf-8")
    # the report's table of the exported commands on the true twin holds the export's own numbers
    table = report[report.index("exported commands sent to the true robot"):]
    for key in ("uncompensated", "torch", "onnx_float64", "onnx_float32"):
        assert f"{truth[key]['position_rms_mm']:.4f}" in table
    manifest = json.loads((exported / "small" / "manifest.json").read_text(encoding="utf-8"))
    assert sorted(manifest["files"]) == ["compensator", "compensator_f32", "monitor", "monitor_f32"]
    assert json.loads((out / "small" / "metrics.json").read_text(encoding="utf-8"))["export"] == summary["export"]
    # the turned-tool warning of an export for the flange, where its convergence report counts such poses
    turned = manifest["convergence"]["strata"]["uniform"]["share_tool_turn_added_above_1_deg"]
    assert (summary["export"]["turned_tool_warning"] is not None) == (turned > 0)


def _small(out, exported, name="small") -> RunConfig:
    config = RunConfig(name=name, out=str(out), export_dir=str(exported), twin=TwinConfig(seed=3, n_train=60, n_test=30))
    config.fit.residual, config.fit.gravity_compliance, config.fit.joint_harmonics = "none", "none", "none"
    config.fit.progress, config.fit.jobs = False, 1
    return config


@pytest.mark.parametrize("out, export_dir", [("runs", "runs"), ("runs", "runs/small"), ("r3/small", "r3")])
def test_run_and_export_folders_that_coincide_or_nest_are_refused_before_any_work(tmp_path, out, export_dir):
    from torchcal.core.folder import FolderError

    with pytest.raises(FolderError, match="are the same folder or one lies in the other"):
        run(_small(tmp_path / out, tmp_path / export_dir))
    assert not any(tmp_path.iterdir())  # refused before any work: nothing written


@pytest.mark.slow
def test_a_rerun_keeps_files_torchcal_did_not_write(tmp_path):
    from torchcal.core.folder import FolderError

    out, exported = tmp_path / "runs", tmp_path / "exported"
    run(_small(out, exported))
    run(_small(out, exported))  # its own folder: rewritten
    for notes in (out / "small" / "NOTES.txt", out / "small" / "model" / "NOTES.txt"):
        notes.write_text("mine")
        with pytest.raises(FolderError, match="torchcal did not write this"):
            run(_small(out, exported))
        assert notes.read_text() == "mine"
        notes.unlink()


@pytest.mark.slow
def test_an_interrupted_rerun_leaves_the_earlier_run_and_export_a_matching_pair(tmp_path, monkeypatch):
    from torchcal.instruments.tracker import run as run_module

    out, exported = tmp_path / "runs", tmp_path / "exported"
    run(_small(out, exported))
    manifest = (exported / "small" / "manifest.json").read_bytes()
    metrics = (out / "small" / "metrics.json").read_bytes()

    def interrupted(path, data):
        raise KeyboardInterrupt  # after the export was written, before the run folder is in place

    monkeypatch.setattr(run_module, "atomic_write_json", interrupted)
    config = _small(out, exported)
    config.twin.seed = 4
    with pytest.raises(KeyboardInterrupt):
        run(config)
    assert (exported / "small" / "manifest.json").read_bytes() == manifest
    assert (out / "small" / "metrics.json").read_bytes() == metrics
    assert [p.name for p in exported.iterdir()] == ["small"] and [p.name for p in out.iterdir()] == ["small"]


@pytest.mark.slow
def test_a_rerun_without_export_says_the_earlier_export_no_longer_matches(tmp_path):
    out, exported = tmp_path / "runs", tmp_path / "exported"
    run(_small(out, exported))
    config = _small(out, exported)
    config.export = False
    with pytest.warns(UserWarning, match="no longer matches the run's model"):
        run(config)
