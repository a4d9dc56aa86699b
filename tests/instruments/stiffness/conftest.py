"""A stiffness twin case and its default fit, shared by the command-line tests of this package."""

from __future__ import annotations

import pytest

from torchcal.cli import main


@pytest.fixture(scope="session")
def case(tmp_path_factory):
    out = tmp_path_factory.mktemp("stiffness") / "case"
    assert main(["simulate", "instrument=stiffness", "--out", str(out), "n_train=80", "n_test=60", "seed=3"]) == 0
    return out


@pytest.fixture(scope="session")
def fitted(case, tmp_path_factory):
    model = tmp_path_factory.mktemp("fit") / "model"
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "stiffness_train.csv"), "--out", str(model)]) == 0
    return model
