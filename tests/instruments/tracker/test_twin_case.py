"""The tracker twin case on disk: its files, header and noise floor."""

from __future__ import annotations

import json
import math

from torchcal.instruments.tracker.twin_case import write_twin_case
from torchcal.sim.twin import TwinConfig


def test_twin_case_files(tmp_path):
    paths = write_twin_case(tmp_path, TwinConfig(n_train=30, n_test=10, seed=3))
    truth = json.loads(paths["truth.json"].read_text())
    assert math.isclose(truth["noise_floor_rms_mm"], math.sqrt(3 * (0.012**2 + 0.008**2)))
    assert paths["train.csv"].read_text().splitlines()[0] == "q1,q2,q3,q4,q5,q6,x,y,z"
    assert len(paths["test.csv"].read_text().splitlines()) == 11
