"""`torchcal run` with its export checked in a worker beside the report: the same files, numbers and
report as one step after the other."""

from __future__ import annotations

import json

import pytest

from torchcal.config.schema import RunConfig
from torchcal.core.workers import warm_up
from torchcal.instruments.tracker.run import run
from torchcal.sim.twin import TwinConfig


def _run(tmp_path, jobs: int) -> tuple[dict, str]:
    out, exported = tmp_path / f"runs{jobs}", tmp_path / f"exported{jobs}"
    config = RunConfig(name="small", out=str(out), export_dir=str(exported),
                       twin=TwinConfig(seed=2, gravity=True, n_train=150, n_test=60))
    config.fit.residual, config.fit.gravity_compliance, config.fit.joint_harmonics = "none", "elbow+wrist", "none"
    config.fit.progress, config.fit.jobs = False, jobs
    summary = run(config)
    report = (out / "small" / "report.md").read_text(encoding="utf-8")
    manifest = json.loads((exported / "small" / "manifest.json").read_text(encoding="utf-8"))
    for text in (str(out), str(exported)):
        report = report.replace(text, "<folder>")
    summary.pop("elapsed_s")
    return {**summary, "manifest_files": sorted(manifest["files"])}, report


@pytest.mark.slow
def test_export_beside_the_report_writes_what_one_step_after_the_other_writes(tmp_path):
    serial, serial_report = _run(tmp_path, 1)
    warm_up(2, ["torchcal.compensate.export"], wait=True)  # a worker ready when the export starts
    parallel, parallel_report = _run(tmp_path, 2)
    assert parallel_report == serial_report
    assert "compensation_on_true_robot" in serial["export"] and "exported commands sent to the true robot" in serial_report
    text = json.dumps(parallel, sort_keys=True, default=str).replace("exported2", "exported1").replace("runs2", "runs1")
    assert text == json.dumps(serial, sort_keys=True, default=str)
