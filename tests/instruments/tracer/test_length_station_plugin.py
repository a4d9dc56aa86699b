"""The one-station instrument on its own: recognition, options, and its twin against the truth."""

from __future__ import annotations

import json

import pytest

from torchcal.cli import main
from torchcal.core.errors import DataError, TorchcalError
from torchcal.instruments.registry import get, recognise
from torchcal.instruments.tracer.commands import TracerFitConfig
from torchcal.instruments.tracer.one_station.commands import length_station_config
from torchcal.instruments.tracer.one_station.twin import (
    LengthStationTwinConfig,
    write_length_station_case,
)
from torchcal.kinematics.robot import load_robot


def _header_file(tmp_path, header: str):
    path = tmp_path / "f.csv"
    path.write_text(header + "\n" + ",".join("1" for _ in header.split(",")) + "\n")
    return path


def test_a_single_length_column_is_a_length_station_and_two_are_a_tracer(tmp_path):
    assert recognise(_header_file(tmp_path, "q1,q2,q3,q4,q5,q6,l1")).name == "length_station"
    assert recognise(_header_file(tmp_path, "q1,q2,q3,q4,q5,q6,l1,l2,l3,l4")).name == "tracer"
    assert not get("tracer").recognises({"q1", "l1"})
    assert not get("length_station").recognises({"q1", "l1", "l2"})


def test_each_instrument_has_only_its_own_options():
    assert {"structure", "refit_anchor", "check_limits"}.isdisjoint(TracerFitConfig.__dataclass_fields__)
    with pytest.raises(TorchcalError, match="structure must be auto or one of nominal, offsets, full"):
        length_station_config(["structure=everything"])
    with pytest.raises(TorchcalError, match="cv_folds"):
        length_station_config(["cv_folds=1"])
    with pytest.raises(TorchcalError):
        length_station_config(["tracer_method=joint"])  # a tracer option is unknown here


def test_twin_refuses_settings_without_a_physical_meaning():
    with pytest.raises(TorchcalError, match="n_train"):
        LengthStationTwinConfig(n_train=5)
    with pytest.raises(TorchcalError, match="noise_mm"):
        LengthStationTwinConfig(noise_mm=-1.0)
    with pytest.raises(TorchcalError, match="anchor_mm"):
        LengthStationTwinConfig(anchor_mm=[1.0, 2.0])


def test_fit_on_its_twin_finds_the_true_anchor_and_offset(tmp_path):
    files = write_length_station_case(tmp_path / "twin", LengthStationTwinConfig(n_train=120, n_test=60))
    truth = json.loads(files["truth.json"].read_text())
    model = tmp_path / "model"
    assert main(["fit", "--robot", str(files["robot.yaml"]), "--data", str(files["lengths.csv"]), "--out", str(model)]) == 0
    station = json.loads((model / "calibration.json").read_text())["length_station"]
    # the anchor absorbs what the gauge leaves free (row 1 of the table, the base frame), so it is
    # compared with the truth to well under the robot errors (0.3 mm lengths, 0.5 mm tool)
    distance = sum((a - b) ** 2 for a, b in zip(station["anchor_mm"], truth["anchor_mm"])) ** 0.5
    assert distance < 2.0, station["anchor_mm"]
    assert abs(station["offset_mm"] - truth["offset_mm"]) < 0.5
    assert station["length_rms_mm"] < 2 * truth["noise_mm"]
    out = tmp_path / "metrics.json"
    assert main(["evaluate", "--model", str(model), "--data", str(files["test.csv"]), "--json", str(out)]) == 0
    held_out = json.loads(out.read_text())["length_rms_mm"]
    assert held_out < 1.5 * truth["noise_mm"]


def test_a_file_with_too_few_rows_is_refused_naming_the_file(tmp_path):
    files = write_length_station_case(tmp_path / "twin", LengthStationTwinConfig(n_train=20, n_test=5))
    with pytest.raises(DataError, match="too few"):
        get("length_station").load(files["test.csv"], load_robot(files["robot.yaml"]))
