"""The calibration report of ``fit`` and ``evaluate --report`` on a small twin: what it states, and that it is right."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch

from torchcal.cli import main
from torchcal.data.measurements import load_measurements
from torchcal.instruments.tracker.report import ReportInputs, calibration_report, score_pose_set
from torchcal.report.document import Figure, Paragraph, Table
from torchcal.stages.geometry import held_out_errors
from torchcal.stages.store import load_model

FIT_TABLES = {"accuracy", "model_selection", "per_axis", "worst_poses_1", "frames", "parameters", "compensator"}


def _tables(page: str) -> set[str]:
    return set(re.findall(r'data-table="([^"]+)"', page))


def _markdown_table(md: str, first_header: str) -> list[list[str]]:
    lines = md.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header} |"))
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split(" | ")])
    return rows


def test_fit_writes_both_reports_into_the_model_folder(reported):
    model = reported["model"]
    md, page = (model / "report.md").read_text(), (model / "report.html").read_text()
    assert _tables(page) >= FIT_TABLES
    # every figure the Markdown links exists and is the one inlined in the HTML
    linked = re.findall(r"\]\((figures/[^)]+\.png)\)", md)
    assert len(linked) >= 6 and all((model / f).is_file() for f in linked)
    assert len(re.findall(r'src="data:image/png;base64,', page)) == len(linked)
    # the protocol stands next to the numbers: training figures are marked optimistic, CV ones held out
    accuracy = _markdown_table(md, "file")
    protocols = {row[1]: row[2] for row in accuracy}
    assert "optimistic" in protocols["geometry"] and "held out" in protocols["geometry, cross-validated"]
    assert "tool fitted" in protocols["nominal"]
    # the report files belong to the folder: listed with their checksums, and the folder still loads
    listed = json.loads((model / "checksums.json").read_text())["files"]
    assert {"report.md", "report.html"} <= set(listed)
    load_model(model)


def test_evaluate_report_names_the_worst_poses_by_their_file_rows(reported):
    md = (reported["evaluation"] / "report.md").read_text()
    stored = load_model(reported["model"])
    data = load_measurements(reported["case"] / "test.csv", stored.robot)
    error = held_out_errors(stored, data).norm(dim=-1) * 1e3
    order = torch.argsort(error, descending=True)
    worst = _markdown_table(md, "row")
    # the test file has a blank line after its header: the first pose is row 3
    assert data.line_numbers[0] == 3
    assert [int(r[0]) for r in worst[:3]] == [data.line_numbers[i] for i in order[:3].tolist()]
    assert float(worst[0][1]) == pytest.approx(float(error[order[0]]), abs=1e-4)
    assert "held-out file test.csv, never fitted" in md
    # the fit calibrated its prediction uncertainty: the evaluation shows it against what was measured
    assert "## Predicted and observed uncertainty" in md and "carries no prediction uncertainty" not in md


def test_evaluate_report_refuses_the_model_folder_and_a_file(reported, tmp_path, capsys):
    args = ["evaluate", "--model", str(reported["model"]), "--data", str(reported["case"] / "test.csv"), "--report"]
    before = (reported["model"] / "report.md").read_text()
    assert main([*args, str(reported["model"])]) == 2
    assert "model folder" in capsys.readouterr().err
    assert (reported["model"] / "report.md").read_text() == before
    (tmp_path / "f").write_text("x")
    assert main([*args, str(tmp_path / "f")]) == 2


def test_uncertainty_section_shows_predicted_against_observed(reported):
    stored = load_model(reported["model"])
    data = load_measurements(reported["case"] / "test.csv", stored.robot)
    pose_set = score_pose_set(stored, data, held_out=True)
    observed = np.linalg.norm(pose_set.delivered.mm, axis=1)
    predicted = list(np.full(len(observed), float(np.percentile(observed, 95))))
    unc = {"coverage_95": 0.95, "predicted_p95_mm": predicted[0], "observed_p95_mm": float(np.percentile(observed, 95)),
           "per_pose_predicted_p95_mm": predicted}
    with_unc = calibration_report("t", stored, [pose_set], ReportInputs(uncertainty=unc))
    section = next(s for s in with_unc.sections if s.heading == "Predicted and observed uncertainty")
    assert any(isinstance(b, Figure) and b.name == "uncertainty" for b in section.blocks)
    table = next(b for b in section.blocks if isinstance(b, Table))
    assert table.rows[0][2] == "95.0 %"
    assert not any(isinstance(b, Paragraph) and "carries no prediction" in b.text for b in section.blocks)
    # without the metric the section says the model has none
    without = calibration_report("t", stored, [pose_set], ReportInputs())
    section = next(s for s in without.sections if s.heading == "Predicted and observed uncertainty")
    assert any(isinstance(b, Paragraph) and "This model carries no prediction uncertainty" in b.text
               for b in section.blocks)


def test_report_and_json_frames_are_the_whole_transform(reported):
    """The instrument frame and tool in report and calibration.json are the twin's, up to what row 1 and d6 absorb."""
    md = (reported["model"] / "report.md").read_text()
    meta = json.loads((reported["model"] / "calibration.json").read_text())
    truth = json.loads((reported["case"] / "truth.json").read_text())
    frame = meta["frames"]["T_instrument_base"]
    row = next(r for r in _markdown_table(md, "transform") if r[0].startswith("T_instrument_base"))
    assert float(row[1].split(" ± ")[0]) == pytest.approx(frame["x"], abs=1e-4)
    # the twin stands its tracker about 2.5 m away: a correction near zero would miss by metres
    assert np.abs(np.array([frame[a] for a in "xyz"]) - truth["T_instrument_base"]["translation_mm"]).max() < 3.0
    tool = meta["frames"]["T_flange_tool"]
    assert np.abs(np.array([tool[a] for a in "xyz"]) - truth["tool_mm"]).max() < 2.0


def test_fit_report_names_the_calibrated_robot_files_and_what_they_cannot_hold(reported):
    md = (reported["model"] / "report.md").read_text()
    section = md.split("## Calibrated robot files", 1)[1].split("\n## ", 1)[0]
    assert "calibrated_robot.urdf" in section and "residual head" in section and "calibration.json" in section


def test_orientation_rows_say_training_or_held_out_as_the_position_rows_do(reported):
    from dataclasses import replace

    from torchcal.instruments.tracker.report import structure_name
    from torchcal.stages.geometry import model_joints

    stored = load_model(reported["model"])
    data = load_measurements(reported["case"] / "test.csv", stored.robot)
    with torch.no_grad():  # the model's own flange orientations (with its joint-space terms): a file that measured them
        flange = stored.model.instrument_from_base(stored.x) @ stored.model.base_flange_pose(model_joints(stored, data.q),
                                                                                             stored.x)
    data = replace(data, rotation=flange[..., :3, :3])
    held_out, training = score_pose_set(stored, data, held_out=True), score_pose_set(stored, data, held_out=False)
    assert [name for name, _ in held_out.orientation] == ["nominal", structure_name(stored)]
    assert "optimistic" not in held_out.orientation[1][1].protocol
    assert "optimistic" in training.orientation[1][1].protocol
    assert held_out.orientation[1][1].metrics()["orientation_max_deg"] < 1e-6  # its own orientations, probe fitted
