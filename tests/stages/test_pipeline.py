"""The one fit pipeline: the same model folder as the steps it sequences, and a typed outcome."""

from __future__ import annotations

import json

import torch

from torchcal.config.schema import FitConfig
from torchcal.core.threads import fit_threads
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit_with_selection, save_fit
from torchcal.stages.pipeline import NO_HEADS, fit_model
from torchcal.stages.residual import fit_residual_stage
from torchcal.stages.store import load_model


def _data(n: int = 160):
    twin = Twin.create(TwinConfig(seed=3))
    return twin.robot, twin.sample(n, torch.Generator().manual_seed(5))


def test_pipeline_matches_its_steps_and_types_the_head(tmp_path):
    robot, train = _data()
    config = FitConfig(residual="elm", residual_hidden=20, progress=False, gravity_compliance="none",
                       joint_harmonics="none")
    run = fit_model(tmp_path / "pipeline", robot, train, config)
    # the steps by hand, independently of the pipeline, on its thread count (the tables are compared to the bit)
    with fit_threads():
        result, structure = fit_with_selection(robot, train, config)
        save_fit(tmp_path / "steps", robot, train, result, {}, structure=structure, uncertainty=config.uncertainty)
        by_hand = fit_residual_stage(tmp_path / "steps", train, config, structure=structure)
    a, b = load_model(run.folder), load_model(tmp_path / "steps")
    assert torch.equal(a.x, b.x) and (a.residual is None) == (b.residual is None)
    assert run.residual is not None and run.residual.decision == by_hand.decision
    assert run.head == by_hand.kept == run.residual.comparison.chosen_head
    # rows of stopped heads hold NaN, so the tables are compared as written
    assert json.dumps(run.residual.to_dict()["comparison"]) == json.dumps(by_hand.comparison.to_dict())
    assert (run.folder / "config.yaml").is_file() and (run.folder / "uncertainty.json").is_file()
    assert run.lines()[-1] == by_hand.decision


def test_no_heads_still_records_the_structure_choice(tmp_path):
    robot, train = _data()
    config = FitConfig(residual="none", progress=False, gravity_compliance="auto", joint_harmonics="none")
    result, structure = fit_with_selection(robot, train, config)
    run = fit_model(tmp_path / "m", robot, train, config, fitted=(result, structure), metadata=lambda r: {"k": 1})
    assert run.residual is None and run.head is None and run.result is result
    selection = json.loads((run.folder / "model_selection.json").read_text())
    assert selection["residual_decision"] == NO_HEADS
    assert selection["chosen"] == structure.comparison.chosen == run.comparison.chosen
    assert json.loads((run.folder / "calibration.json").read_text())["k"] == 1
