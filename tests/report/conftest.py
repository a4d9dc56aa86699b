"""One small twin fitted and evaluated through the command line, shared by the report tests."""

from __future__ import annotations

import pytest

from torchcal.cli import main


@pytest.fixture(scope="session")
def reported(tmp_path_factory):
    """``simulate`` (120 + 60 poses), ``fit`` (gravity compliance chosen by CV, no head) and ``evaluate --report``.

    The test file gets a blank line after its header, so that its rows (as the file's errors
    name them) differ from 1 + the pose index.
    """
    root = tmp_path_factory.mktemp("reported")
    case, model, report = root / "case", root / "model", root / "evaluation"
    assert main(["simulate", "--out", str(case), "n_train=120", "n_test=60", "seed=3"]) == 0
    lines = (case / "test.csv").read_text().splitlines()
    (case / "test.csv").write_text("\n".join([lines[0], "", *lines[1:]]) + "\n")
    assert main(["fit", "--robot", str(case / "robot.yaml"), "--data", str(case / "train.csv"), "--out", str(model),
                 "residual=none", "joint_harmonics=none", "progress=false"]) == 0
    assert main(["evaluate", "--model", str(model), "--data", str(case / "test.csv"), "--report", str(report)]) == 0
    return {"case": case, "model": model, "evaluation": report}
