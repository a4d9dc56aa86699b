"""The one rule for output paths: torchcal replaces only what it wrote for the same purpose."""

from __future__ import annotations

import json

import pytest

from torchcal.core.folder import staged_folder, write_member_json
from torchcal.core.outputs import (
    JSON_KEY,
    OutputClaimError,
    check_name,
    claim_file,
    claim_folder,
    csv_with_header,
    folder_purpose,
    is_metrics_json,
)


def _model(path):
    write_member_json(path, "calibration.json", {"format": "torchcal-model/1"})
    return path


def test_purpose_from_stamp_and_from_legacy_markers(tmp_path):
    with staged_folder(tmp_path / "report", purpose="report", sealed=False) as staging:
        (staging / "report.md").write_text("# r\n")
    assert folder_purpose(tmp_path / "report") == "report"
    assert folder_purpose(_model(tmp_path / "model")) == "model"
    write_member_json(tmp_path / "export", "manifest.json", {})
    assert folder_purpose(tmp_path / "export") == "export"
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("x")
    assert folder_purpose(tmp_path / "mine") is None


@pytest.mark.parametrize("purpose, accepted", [("model", True), ("export", False), ("report", False), ("twin", False)])
def test_a_folder_is_replaced_only_for_its_own_purpose(tmp_path, purpose, accepted):
    model = _model(tmp_path / "model")
    if accepted:
        claim_folder(model, purpose)
    else:
        with pytest.raises(OutputClaimError, match="a model folder"):
            claim_folder(model, purpose)


def test_absent_and_empty_folders_are_accepted_foreign_ones_refused(tmp_path):
    claim_folder(tmp_path / "new" / "deeper", "export")
    (tmp_path / "empty").mkdir()
    claim_folder(tmp_path / "empty", "twin")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("x")
    with pytest.raises(OutputClaimError, match="not a torchcal output"):
        claim_folder(tmp_path / "mine", "report")


def test_nothing_is_written_inside_another_output(tmp_path):
    model = _model(tmp_path / "model")
    with pytest.raises(OutputClaimError, match="inside a model folder"):
        claim_folder(model / "report", "report", "--report")
    with pytest.raises(OutputClaimError, match="inside a model folder"):
        claim_file(model / "checksums.json", "metrics", "--json", is_metrics_json)
    study = tmp_path / "study"
    with staged_folder(study, purpose="study", sealed=False):
        pass
    with pytest.raises(OutputClaimError, match="inside a study folder"):
        claim_folder(study / "best", "run")
    claim_folder(study / "best", "run", within=("study",))


def test_files_are_replaced_only_when_torchcal_wrote_them(tmp_path):
    mine = tmp_path / "mine.json"
    mine.write_text('{"a": 1}')
    with pytest.raises(OutputClaimError, match="not a metrics file"):
        claim_file(mine, "metrics", "--json", is_metrics_json)
    ours = tmp_path / "ours.json"
    ours.write_text(json.dumps({JSON_KEY: "metrics", "position_rms_mm": 0.1}))
    claim_file(ours, "metrics", "--json", is_metrics_json)
    trajectory = tmp_path / "traj.csv"
    trajectory.write_text("t,q1,q2\n0,1,2\n")
    claim_file(trajectory, "trajectory", "--out", csv_with_header(lambda h: h[0] == "t"))
    with pytest.raises(OutputClaimError, match="existing folder"):
        claim_file(tmp_path, "metrics", "--json", is_metrics_json)


@pytest.mark.parametrize("name", ["..", "../x", "a/b", ".hidden", "", "x" * 101, "a b", "na\u00efve"])
def test_names_that_could_leave_their_folder_are_refused(name):
    with pytest.raises(OutputClaimError, match="one folder name"):
        check_name(name, "name=")


def test_plain_names_pass():
    assert check_name("twin-default_2.v1+mlp", "name=") == "twin-default_2.v1+mlp"
