"""``parameters=auto``: grouped cross-validation chooses between classic and full stiffness models.

On the standard twin (joints yield only about their axes) the simpler classic model is kept; on
a twin whose joints also yield off their axes (``off_axis``) the 6-D diagonal is. Either way the
default predicts held-out deflection as well as the better of the two fitted explicitly.
"""

from __future__ import annotations

import contextlib
import io
import json

import pytest
import torch

from torchcal.core.errors import TorchcalError
from torchcal.instruments.stiffness.commands import (
    evaluate_stiffness,
    fit_stiffness,
    stiffness_config,
)
from torchcal.instruments.stiffness.twin import OFF_AXIS_LEVER_M, StiffnessTwin, StiffnessTwinConfig
from torchcal.instruments.stiffness.twin_case import StiffnessCaseConfig, write_stiffness_twin_case

OFF_AXIS = {"standard": 0.0, "off_axis": 0.05}
EXPECTED = {"standard": "classic", "off_axis": "full"}


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    """Case files (seed 3, 80 training and 60 test poses) of the standard and the off-axis twin."""
    root = tmp_path_factory.mktemp("selection")
    return {
        twin: write_stiffness_twin_case(root / twin, StiffnessCaseConfig(seed=3, n_train=80, n_test=60, off_axis=off))
        for twin, off in OFF_AXIS.items()
    }


@pytest.fixture(scope="module", params=list(OFF_AXIS))
def fits(request, cases, tmp_path_factory):
    """Twin name, its case, the stderr of the default fit, and each fit's folder and held-out deflection RMS (mm)."""
    paths = cases[request.param]
    root = tmp_path_factory.mktemp(request.param)
    folders, rms, console = {}, {}, io.StringIO()
    for parameters in ("auto", "classic", "full"):
        overrides = [] if parameters == "auto" else [f"parameters={parameters}"]
        outcome = fit_stiffness(paths["robot.yaml"], paths["stiffness_train.csv"], root / parameters, overrides)
        folders[parameters] = outcome.folder
        if parameters == "auto":
            console.write("\n".join(outcome.lines))
        rms[parameters] = evaluate_stiffness(folders[parameters], paths["stiffness_test.csv"], [])["deflection_rms_mm"]
    return request.param, paths, console.getvalue(), folders, rms


def test_off_axis_twin_yields_off_the_joint_axes(cases):
    truth = json.loads(cases["off_axis"]["stiffness_truth.json"].read_text())
    c = torch.tensor(truth["compliance_si"], dtype=torch.float64)
    on_axis = c[:, 5, 5]
    assert truth["config"]["off_axis"] == 0.05
    assert torch.allclose(c[:, 3, 3], 0.05 * on_axis) and torch.allclose(c[:, 4, 4], 0.05 * on_axis)
    assert torch.allclose(c[:, 0, 0], 0.05 * on_axis * OFF_AXIS_LEVER_M**2)
    # the on-axis springs are those of the standard twin of the same seed
    assert torch.equal(1.0 / on_axis, StiffnessTwin(StiffnessTwinConfig(seed=3)).joint_stiffness)
    standard = json.loads(cases["standard"]["stiffness_truth.json"].read_text())
    assert "off_axis" not in standard["config"]
    assert torch.count_nonzero(torch.tensor(standard["compliance_si"])) == 6


def test_auto_chooses_by_grouped_cross_validation(fits):
    twin, _, console, folders, _ = fits
    meta = json.loads((folders["auto"] / "stiffness.json").read_text())
    selection = meta["model_selection"]
    assert selection["chosen"] == EXPECTED[twin]
    assert [row["name"] for row in selection["candidates"]] == ["classic", "full"]
    assert "configuration regions" in selection["protocol"]
    assert json.loads((folders["auto"] / "model_selection.json").read_text())["stiffness"]["chosen"] == EXPECTED[twin]
    fitted = set(meta["parameters"]) | set(meta["unobservable"])
    assert (fitted == {f"k_j{i}_rz" for i in range(1, 7)}) == (EXPECTED[twin] == "classic")
    assert "model selection:" in console and f"-> {EXPECTED[twin]}:" in console
    for explicit in ("classic", "full"):  # an explicit choice runs no cross-validation
        assert "model_selection" not in json.loads((folders[explicit] / "stiffness.json").read_text())
        assert not (folders[explicit] / "model_selection.json").exists()


def test_default_predicts_held_out_deflection_as_well_as_the_better_model(fits):
    twin, _, _, _, rms = fits
    better = min(rms["classic"], rms["full"])
    assert rms["auto"] <= 1.05 * better, (twin, rms)
    if twin == "off_axis":  # the joints' off-axis yield is what classic cannot predict
        assert rms["full"] < 0.8 * rms["classic"]


def test_the_stiffness_selection_sits_next_to_a_geometry_selection(cases, tmp_path):
    """``model_selection.json`` keeps what a geometry fit wrote; an explicit refit drops the stiffness part."""
    paths, out = cases["standard"], tmp_path / "m"
    out.mkdir()
    geometry = {"protocol": "geometry CV", "chosen": "geometry", "reason": "r", "candidates": []}
    (out / "model_selection.json").write_text(json.dumps(geometry))
    with contextlib.redirect_stderr(io.StringIO()):
        fit_stiffness(paths["robot.yaml"], paths["stiffness_train.csv"], out, [])
        both = json.loads((out / "model_selection.json").read_text())
        fit_stiffness(paths["robot.yaml"], paths["stiffness_train.csv"], out, ["parameters=classic"])
    assert both["chosen"] == "geometry" and both["stiffness"]["chosen"] == "classic"
    assert json.loads((out / "model_selection.json").read_text()) == geometry


def test_too_few_poses_for_cross_validation_fit_classic(cases, tmp_path):
    lines = cases["standard"]["stiffness_train.csv"].read_text().splitlines()
    small = tmp_path / "small.csv"
    small.write_text("\n".join(lines[:9]) + "\n")
    with pytest.warns(UserWarning, match="parameters=auto: 5-fold cross-validation needs at least 10 poses"):
        folder = fit_stiffness(cases["standard"]["robot.yaml"], small, tmp_path / "m", []).folder
    selection = json.loads((folder / "stiffness.json").read_text())["model_selection"]
    assert selection["chosen"] == "classic" and "no cross-validation" in selection["reason"]


@pytest.mark.parametrize(
    "override, message",
    [("parameters=best", "parameters must be one of auto, classic, full"), ("split=loo", "split must be one of"),
     ("cv_folds=1", r"cv_folds must be a finite number in \[2, 100\], got 1")],
)
def test_bad_selection_options_are_one_clear_error(override, message):
    with pytest.raises(TorchcalError, match=message):
        stiffness_config([override])
    assert stiffness_config([]).parameters == "auto" and stiffness_config([]).split == "grouped"
    config = stiffness_config(["cv_folds=3", "split=blocks", "parameters=full"])
    assert (config.cv_folds, config.split, config.parameters) == (3, "blocks", "full")
