"""calibration.json holds the whole instrument frame and tool (mm, deg, 1-sigma); calibrated_robot.yaml says what it is."""

from __future__ import annotations

import json
import math

import pytest
import torch
import yaml

from torchcal.config.schema import FitConfig
from torchcal.identify.calibrate import calibrate
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.robot import load_robot
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.files import read_tensors
from torchcal.stages.geometry import fit, save_fit
from torchcal.stages.store import load_model


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    twin = Twin.create(TwinConfig(seed=11))
    train = twin.sample(150, torch.Generator().manual_seed(5))
    result = calibrate(twin.robot, train)
    folder = save_fit(tmp_path_factory.mktemp("frames") / "model", twin.robot, train, result, {})
    return twin, folder


def test_json_frame_and_tool_are_the_safetensors_values(fitted):
    """Load the folder, rebuild T_instrument_base and the tool from the tensors, compare with the JSON."""
    _, folder = fitted
    meta = json.loads((folder / "calibration.json").read_text())
    tensors = read_tensors(folder / "calibration.safetensors", {"x": 1, "T_reference": 2, "free": 1, "covariance": 2})
    stored = load_model(folder)
    layout = stored.model.layout
    x = tensors["x"]
    base = x[layout.base_slice]
    transform = tensors["T_reference"] @ tf.homogeneous(tf.so3_exp(base[3:]), base[:3])
    angles = torch.rad2deg(tf.matrix_to_euler_xyz(transform[:3, :3]))
    params = meta["parameters"]
    for k, axis in enumerate("xyz"):
        assert params[f"base_{axis}"]["value"] == pytest.approx(float(transform[k, 3]) * 1e3, abs=1e-9)
        assert params[f"base_r{axis}"]["value"] == pytest.approx(float(angles[k]), abs=1e-9)
        assert params[f"tool_{axis}"]["value"] == pytest.approx(float(x[layout.tool_slice][k]) * 1e3, abs=1e-9)
        assert meta["frames"]["T_instrument_base"][axis] == params[f"base_{axis}"]["value"]
    matrix = torch.tensor(meta["frames"]["T_instrument_base"]["matrix_mm"], dtype=torch.float64)
    assert torch.allclose(matrix[:3, :3], transform[:3, :3], atol=1e-12)
    assert torch.allclose(matrix[:3, 3], transform[:3, 3] * 1e3, atol=1e-9)
    # sigmas: estimated entries have one, and the translation's equals the correction's (rotated: same norm)
    free = set(stored.free_names)
    sigma_t = torch.tensor([params[f"base_{a}"]["sigma"] for a in "xyz"], dtype=torch.float64)
    index = [stored.free_names.index(f"base_{a}") for a in "xyz"]
    cov_t = stored.covariance[index][:, index] * 1e6
    assert {f"base_{a}" for a in "xyz"} <= free and bool((sigma_t > 0).all())
    rotated = transform[:3, :3] @ cov_t @ transform[:3, :3].T
    assert torch.allclose(sigma_t, rotated.diagonal().sqrt(), rtol=1e-9)
    assert params["tool_z"]["sigma"] == pytest.approx(math.sqrt(float(stored.covariance[
        stored.free_names.index("tool_z"), stored.free_names.index("tool_z")])) * 1e3, rel=1e-9)


def test_json_frame_is_the_twins_tracker(fitted):
    """The twin's tracker stands metres away; the JSON holds that pose, not a near-zero correction."""
    twin, folder = fitted
    meta = json.loads((folder / "calibration.json").read_text())
    truth = twin.T_instrument_base()
    frame = meta["frames"]["T_instrument_base"]
    assert torch.linalg.norm(truth[:3, 3]) > 1.0
    # row 1 of the table is absorbed by the frame: they agree to the size of the twin's row-1 errors
    assert max(abs(frame[a] - float(truth[k, 3]) * 1e3) for k, a in enumerate("xyz")) < 3.0
    expected = torch.rad2deg(tf.matrix_to_euler_xyz(truth[:3, :3]))
    assert max(abs(frame[f"r{a}"] - float(expected[k])) for k, a in enumerate("xyz")) < 0.1


def test_calibrated_yaml_is_the_geometry_and_says_what_it_leaves_out(fitted, tmp_path):
    twin, folder = fitted
    text = (folder / "calibrated_robot.yaml").read_text()
    header = " ".join(line[2:] for line in text.splitlines() if line.startswith("#"))
    assert "geometric stage only" in header and "calibration.json" in header
    assert "alpha1" in header and "nominal values" in header  # the parameters the data could not identify
    assert "residual head" in header
    # the table it holds reproduces the stored geometry in the base frame
    stored = load_model(folder)
    (tmp_path / "r.yaml").write_text(text)
    calibrated = load_robot(tmp_path / "r.yaml")
    q = twin.robot.sample_joints(20, torch.Generator().manual_seed(2))
    in_instrument = stored.model.tcp_position(q, stored.x)
    transform = stored.model.instrument_from_base(stored.x)
    in_base = (in_instrument - transform[:3, 3]) @ transform[:3, :3]
    assert torch.allclose(calibrated.tcp_position(q), in_base, atol=1e-9)
    assert yaml.safe_load(text)["kinematics"]["convention"] == "mdh"


def test_calibrated_yaml_names_joint_space_terms(tmp_path):
    twin = Twin.create(TwinConfig(seed=3, gravity=True))
    train = twin.sample(200, torch.Generator().manual_seed(1))
    result = fit(twin.robot, train, FitConfig(gravity_compliance="wrist", joint_harmonics="none", residual="none",
                                             progress=False))
    folder = save_fit(tmp_path / "m", twin.robot, train, result, {})
    header = " ".join(line[2:] for line in (folder / "calibrated_robot.yaml").read_text().splitlines()
                      if line.startswith("#"))
    assert "gravity compliance" in header and "not the model that was fitted" in header


def test_folder_holds_a_calibrated_urdf_of_the_geometry(fitted, tmp_path):
    """calibrated_robot.urdf (listed in checksums.json) reproduces the stored geometry's TCP in base."""
    twin, folder = fitted
    text = (folder / "calibrated_robot.urdf").read_text()
    assert "calibrated_robot.urdf" in json.loads((folder / "checksums.json").read_text())["files"]
    assert "residual head" in text and "instrument-to-base" in text
    (tmp_path / "r.urdf").write_text(text)
    calibrated = load_robot(tmp_path / "r.urdf", end_link="flange_calibrated_tcp")
    stored = load_model(folder)
    q = twin.robot.sample_joints(20, torch.Generator().manual_seed(4))
    transform = stored.model.instrument_from_base(stored.x)
    in_base = (stored.model.tcp_position(q, stored.x) - transform[:3, 3]) @ transform[:3, :3]
    assert torch.allclose(calibrated.tcp_position(q), in_base, atol=1e-9)
