"""torchcal check on a twin whose truth changed after calibration (or did not).

Truth: the twin's true parameters, changed by a known amount in one group (the tool swapped, a
joint re-mastered, a link bent) or moved as a whole (the robot moved: only the frame changes).
12 new poses with new noise each time.
"""

from __future__ import annotations

import json
import math

import pytest
import torch

from torchcal.app.check import check_data
from torchcal.cli import main
from torchcal.data.measurements import write_measurements_csv

MM, DEG = 1e-3, math.pi / 180


CASES = {
    "nothing": ({}, "valid", []),
    "robot moved": ({"base_x": 50 * MM, "base_y": -20 * MM, "base_rz": 1.0 * DEG}, "valid", []),
    "tool swapped": ({"tool_x": 1.0 * MM, "tool_y": -0.5 * MM, "tool_z": 2.0 * MM}, "changed", ["tool"]),
    "joint 3 re-mastered": ({"theta3": 0.05 * DEG}, "changed", ["theta3"]),
    "link 3 bent": ({"alpha3": 0.05 * DEG, "a3": 0.3 * MM}, "changed", ["alpha3", "a3"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_check_names_what_changed(calibrated, case):
    twin, stored = calibrated
    deltas, verdict, names = CASES[case]
    result = check_data(stored, twin.changed(**deltas).sample(12, torch.Generator().manual_seed(101)))
    assert result.verdict == verdict
    assert set(names) <= set(result.changed) and (names or not result.changed)
    if verdict == "changed":
        assert result.best is not None and result.best.delta_bic > 10


def test_check_cli_writes_verdict_and_changed(calibrated, tmp_path, capsys):
    twin, stored = calibrated
    data = twin.changed(theta3=0.05 * DEG).sample(12, torch.Generator().manual_seed(7))
    write_measurements_csv(tmp_path / "few.csv", data.q, data.position)
    code = main(["check", "--model", str(stored.folder), "--data", str(tmp_path / "few.csv"),
                 "--json", str(tmp_path / "check.json"), "--report", str(tmp_path / "report")])
    doc = json.loads((tmp_path / "check.json").read_text())
    assert code == 0 and doc["verdict"] == "changed" and doc["changed"] == ["theta3"]
    assert len(doc["poses"]) == 12 and (tmp_path / "report" / "report.html").is_file()
    assert "verdict: changed; changed: theta3" in capsys.readouterr().out


def test_check_and_update_refuse_a_file_of_another_robot_and_take_its_units(calibrated, tmp_path, capsys):
    twin, stored = calibrated
    data = twin.sample(12, torch.Generator().manual_seed(9))
    swapped = data.position[:, [1, 0, 2]]  # x and y columns exchanged: a mirrored robot, no frame maps it on this one
    write_measurements_csv(tmp_path / "swapped.csv", data.q, swapped)
    for command in (["check"], ["update", "--out", str(tmp_path / "new")]):
        code = main([*command, "--model", str(stored.folder), "--data", str(tmp_path / "swapped.csv")])
        err = capsys.readouterr().err
        assert code == 2 and "misses these poses by" in err and "even with the instrument frame and the tool point" in err
        assert err.count("\n") == 1
    assert not (tmp_path / "new").exists()
    # the points in metres: the refusal names length_unit=m, and both commands take it
    metres = tmp_path / "metres.csv"
    metres.write_text("".join(line if i == 0 else ",".join(
        f"{float(v) / 1000:.9g}" if j >= data.q.shape[1] else v for j, v in enumerate(line.rstrip("\n").split(","))) + "\n"
        for i, line in enumerate(_csv_lines(tmp_path, data))))
    assert main(["check", "--model", str(stored.folder), "--data", str(metres)]) == 2
    assert "length_unit=m" in capsys.readouterr().err
    assert main(["check", "--model", str(stored.folder), "--data", str(metres), "length_unit=m"]) == 0
    assert "verdict: valid" in capsys.readouterr().out
    assert main(["update", "--model", str(stored.folder), "--data", str(metres), "--out", str(tmp_path / "new"),
                 "length_unit=m"]) == 0
    assert (tmp_path / "new" / "calibration.json").is_file()


def _csv_lines(tmp_path, data) -> list[str]:
    write_measurements_csv(tmp_path / "plain.csv", data.q, data.position)
    return (tmp_path / "plain.csv").read_text().splitlines(keepends=True)


def test_a_long_new_tool_is_a_changed_tool_not_another_robot(calibrated):
    # 100 mm more tool: tens of mm off with the frame alone, which only the tool explains
    twin, stored = calibrated
    result = check_data(stored, twin.changed(tool_x=20 * MM, tool_z=100 * MM).sample(12, torch.Generator().manual_seed(5)))
    assert result.verdict == "changed" and result.changed == ["tool"]


def _corner(twin, n, generator):
    """Poses in a 40 deg box of every joint (a calibration measured in one small region)."""
    from torchcal.data.measurements import Measurements

    low = torch.tensor([-20.0, -100.0, 20.0, -30.0, 30.0, -30.0], dtype=torch.float64) * DEG
    q = low + 40.0 * DEG * torch.rand(n, twin.robot.dof, generator=generator, dtype=torch.float64)
    return Measurements(q=q, position=twin.measure(q, generator))


@pytest.fixture(scope="module")
def calibrated_in_a_corner(tmp_path_factory):
    from torchcal.config.schema import FitConfig
    from torchcal.sim.twin import Twin, TwinConfig
    from torchcal.stages.pipeline import fit_model
    from torchcal.stages.store import load_model

    twin = Twin.create(TwinConfig(seed=3, gravity=False, gear=False))
    folder = tmp_path_factory.mktemp("corner") / "model"
    fit_model(folder, twin.robot, _corner(twin, 150, torch.Generator().manual_seed(11)),
              FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none", progress=False))
    return twin, load_model(folder)


def test_check_outside_the_fitted_region_says_extrapolating_not_changed(calibrated_in_a_corner, capsys):
    """Nothing changed on the robot; the new poses lie across its whole range, the model was fitted in a
    corner: the check must not name a part as changed (it did: link5, dBIC +21)."""
    from torchcal.model_selection.leakage import far_from_training

    twin, stored = calibrated_in_a_corner
    wide = twin.sample(12, torch.Generator().manual_seed(32))
    result = check_data(stored, wide)
    far, radius = far_from_training(stored.robot, stored.training_q, wide.q)
    assert result.n_far == int(far.sum()) >= 6 and result.far_radius_mm == radius
    # the evidence that used to name a part as changed is there, and it is called what it is
    assert result.best is not None and (result.best.delta_bic > 10 or result.exceedance_p < 0.01)
    assert result.verdict == "extrapolating" and result.to_dict()["verdict"] == "extrapolating"
    assert "a change of the robot cannot be told" in result.lines()[-1]
    from torchcal.app.update import (
        resolve_free,  # update extends the model to these poses and says so
    )

    names, how = resolve_free("auto", stored, result)
    assert names == result.best.names and "no change of the robot is claimed" in how
    # inside the corner the same model still names a real change
    moved = check_data(stored, _corner(twin.changed(theta3=0.05 * DEG), 12, torch.Generator().manual_seed(33)))
    assert moved.n_far < 6 and moved.verdict == "changed" and "theta3" in moved.changed
