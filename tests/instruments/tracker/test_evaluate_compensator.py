"""``evaluate``'s account of the compensator is the exported one's, for a model fitted with orientations too."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from torchcal.compensate.export import export_model
from torchcal.config.schema import FitConfig
from torchcal.data.measurements import load_measurements, write_measurements_csv
from torchcal.instruments.tracker.evaluate import score
from torchcal.kinematics import transforms as tf
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit, save_fit
from torchcal.stages.store import load_model


@pytest.fixture(scope="module")
def six_d(tmp_path_factory):
    """A twin measured with a probe mounted at 90 deg about the flange axis (rx, ry, rz too), fitted and exported."""
    root = tmp_path_factory.mktemp("six_d")
    twin = Twin.create(TwinConfig(seed=7, gravity=False, gear=False))
    generator = torch.Generator().manual_seed(3)
    q = twin.robot.sample_joints(80, generator, margin=math.radians(5))
    flange = twin.T_instrument_base() @ twin.model.base_flange_pose(q, twin.x_true)
    probe = tf.so3_exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    angles = tf.matrix_to_euler_xyz(flange[..., :3, :3] @ probe) * (180.0 / np.pi)
    write_measurements_csv(root / "train.csv", q, twin.measure(q, generator),
                           extra={"rx": angles[:, 0], "ry": angles[:, 1], "rz": angles[:, 2]})
    data = load_measurements(root / "train.csv", twin.robot)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        config = FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none", progress=False)
        folder = save_fit(root / "model", twin.robot, data, fit(twin.robot, data, config), {})
        manifest = export_model(folder, root / "export")
    return folder, data, manifest


@pytest.mark.slow
def test_evaluate_states_the_exported_compensators_corrections(six_d):
    folder, data, manifest = six_d
    stored = load_model(folder)
    assert stored.model.with_orientation and abs(float(stored.x[stored.model.layout.tool_slice][5])) > 1.0  # the probe's turn
    comp = score(stored, data, leakage=False).metrics["compensator"]
    # the flange is served, as by the export: the probe's 90 deg mounting is no orientation error of the robot
    assert comp["orientation_deviation_median_rad"] < 1e-6
    exported = manifest["corrections"]["extent"]["training poses"]
    assert comp["corrections"]["n_poses"] == exported["n_poses"]
    assert comp["corrections"]["largest_joint_correction_deg"] == pytest.approx(exported["largest_joint_correction_deg"],
                                                                              rel=1e-9)
