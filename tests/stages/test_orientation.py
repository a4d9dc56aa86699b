"""Orientation scoring against a twin's known orientations."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from torchcal.core.errors import DataError
from torchcal.data.measurements import Measurements
from torchcal.kinematics import transforms as tf
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import nominal_fit
from torchcal.stages.orientation import (
    PROBE_FITTED,
    angles_to_measured,
    model_orientation_errors,
    nominal_orientation_errors,
    orientation_source_of,
    oriented_joints,
    refuse_implausible,
)

PROBE = tf.so3_exp(torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64))  # a probe mounted at some angle


def _geometric_twin(**true_deltas: float) -> Twin:
    twin = Twin.create(TwinConfig(gear=False, gravity=False, angle_error_deg=0.0, length_error_mm=0.0, tool_error_mm=0.0))
    return twin.changed(**true_deltas)


def _measured(twin: Twin, n: int = 60) -> Measurements:
    """Exact positions and orientations of the probe (mounted at :data:`PROBE` on the flange)."""
    q = twin.robot.sample_joints(n, torch.Generator().manual_seed(4))
    flange = twin.T_instrument_base() @ twin.model.base_flange_pose(q, twin.x_true)
    return Measurements(q=q, position=twin.true_positions(q), rotation=flange[..., :3, :3] @ PROBE)


def test_the_truth_leaves_no_error_once_the_probe_rotation_is_fitted():
    twin = _geometric_twin(alpha4=math.radians(0.5))
    data = _measured(twin)
    flange = twin.T_instrument_base() @ twin.model.base_flange_pose(data.q, twin.x_true)
    assert float(angles_to_measured(flange[..., :3, :3], data.rotation, fit_probe=True).max()) < 1e-12
    # without the fitted probe rotation the whole mounting angle is counted
    counted = angles_to_measured(flange[..., :3, :3], data.rotation, fit_probe=False)
    torch.testing.assert_close(counted, tf.rotation_angle(PROBE).expand(len(data)), rtol=0, atol=1e-12)


def test_a_joint_6_zero_offset_is_a_probe_rotation_and_not_counted():
    # theta6 turns the flange about its own axis by a constant: the fitted probe rotation takes it
    data = _measured(_geometric_twin(theta6=math.radians(0.8)))
    _, frame, _ = nominal_fit(_geometric_twin().robot, data)
    scored = nominal_orientation_errors(_geometric_twin().robot, data, frame)
    assert scored.metrics()["orientation_max_deg"] < 1e-6
    assert PROBE_FITTED in scored.protocol


def test_a_tilted_wrist_axis_is_counted_pose_by_pose_in_proportion():
    # alpha4 turns everything after joint 4 about the forearm: an orientation error that varies with the pose,
    # of the tilt's size, and (small angles) three times as large for three times the tilt
    robot = _geometric_twin().robot
    rms = {}
    for delta_deg in (0.2, 0.6):
        data = _measured(_geometric_twin(alpha4=math.radians(delta_deg)))
        _, frame, _ = nominal_fit(robot, data)
        metrics = nominal_orientation_errors(robot, data, frame).metrics()
        assert metrics["n_poses"] == len(data)
        assert 0.5 * delta_deg < metrics["orientation_rms_deg"] < 1.5 * delta_deg
        rms[delta_deg] = metrics["orientation_rms_deg"]
    assert rms[0.6] / rms[0.2] == pytest.approx(3.0, rel=0.01)


def test_the_fitted_probe_rotation_is_the_least_squares_one(generator):
    # chordal least squares: any other constant rotation fits the measured orientations worse
    twin = _geometric_twin(alpha4=math.radians(0.6))
    data = _measured(twin)
    flange = (twin.T_instrument_base() @ twin.model.base_flange_pose(data.q, _geometric_twin().x_true))[..., :3, :3]
    measured = data.rotation
    fitted = tf.project_to_so3((flange.transpose(-1, -2) @ measured).sum(0))

    def chordal(rotation: torch.Tensor) -> float:
        return float((flange @ rotation - measured).pow(2).sum())

    best = chordal(fitted)
    for _ in range(12):
        nudge = tf.so3_exp(torch.randn(3, generator=generator, dtype=torch.float64) * 1e-3)
        assert chordal(fitted @ nudge) > best


def test_orientation_columns_of_another_convention_are_refused():
    robot = _geometric_twin().robot
    data = _measured(_geometric_twin(alpha4=math.radians(0.3)))
    _, frame, _ = nominal_fit(robot, data)
    refuse_implausible(nominal_orientation_errors(robot, data, frame), data)  # a real arm's tenths of a degree pass
    # the file holds the inverse rotations (probe-to-instrument read the other way round)
    inverted = replace(data, rotation=data.rotation.transpose(-1, -2))
    with pytest.raises(DataError, match="convention"):
        refuse_implausible(nominal_orientation_errors(robot, inverted, frame), inverted)


def test_a_position_only_model_is_scored_by_the_orientation_its_compensator_acts_on(tmp_path):
    # a position-only fit's joint-space terms correct positions and not the tool's orientation (the compensator's
    # default source, docs/prior.md): a 0.5 deg harmonic on joint 5 leaves the scored orientation as it was
    import warnings

    from torchcal.identify.calibrate import calibrate
    from torchcal.identify.harmonics import JointHarmonics
    from torchcal.identify.joint_errors import JointSpaceErrors
    from torchcal.identify.prior import PriorSpec
    from torchcal.stages.geometry import save_fit
    from torchcal.stages.store import load_model

    twin = _geometric_twin(alpha4=math.radians(0.3))
    data = _measured(twin)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = calibrate(twin.robot, replace(data, rotation=None), prior=PriorSpec())
    stored = load_model(save_fit(tmp_path / "m", twin.robot, replace(data, rotation=None), result, {}))
    assert orientation_source_of(stored.model) == "geometry"
    coefficients = torch.zeros(2, 6, dtype=torch.float64)
    coefficients[0, 4] = math.radians(0.5)
    terms = JointSpaceErrors(harmonics=JointHarmonics(coefficients))
    with_terms = replace(stored, metadata={**stored.metadata, **terms.to_metadata()})
    plain = model_orientation_errors(stored, data).angles_rad
    torch.testing.assert_close(model_orientation_errors(with_terms, data).angles_rad, plain, rtol=0, atol=1e-12)
    assert torch.equal(oriented_joints(with_terms, data.q), data.q)
    # a 6-D fit's model is oriented by the whole chain: the joints it turns carry the harmonic
    whole = replace(with_terms, model=replace_orientation(with_terms.model))
    assert orientation_source_of(whole.model) == "model"
    turned = oriented_joints(whole, data.q)[:, 4] - data.q[:, 4]
    torch.testing.assert_close(turned, math.radians(0.5) * data.q[:, 4].sin(), rtol=0, atol=1e-15)


def replace_orientation(model):
    """The same error model, marked as fitted to measured orientations."""
    from torchcal.kinematics.error_model import ErrorModel

    return ErrorModel(model.robot, with_orientation=True, parallel_threshold_deg=model.parallel_threshold_deg,
                      T_instrument_base=model.T_reference, device=model.device)


def test_the_orientation_source_is_the_measured_ones_or_the_one_asked_for():
    from torchcal.kinematics.error_model import ErrorModel

    robot = _geometric_twin().robot
    assert orientation_source_of(ErrorModel(robot)) == "geometry"
    assert orientation_source_of(ErrorModel(robot, with_orientation=True)) == "model"
    assert orientation_source_of(ErrorModel(robot), "model") == "model"
    with pytest.raises(ValueError, match="orientation_source"):
        orientation_source_of(ErrorModel(robot), "tool")
