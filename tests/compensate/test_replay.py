"""The replay of measured poses through a compensator's commands, against a twin's truth at the commands."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from torchcal.compensate.export_checks import regular_poses
from torchcal.compensate.replay import (
    command_sets,
    confirmed_share,
    errors_of_true_poses,
    replay,
    solved_mask,
)
from torchcal.data.measurements import Measurements
from torchcal.identify.calibrate import calibrate
from torchcal.identify.prior import PriorSpec
from torchcal.kinematics import transforms as tf
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import save_fit
from torchcal.stages.store import load_model

PROBE = tf.so3_exp(torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64))  # the nest's rotation on the flange


def _measured(twin: Twin, q: torch.Tensor) -> Measurements:
    """The twin's exact measured point and probe orientation at ``q`` (a geometric twin: no gear, no gravity)."""
    flange = twin.T_instrument_base() @ twin.model.base_flange_pose(q, twin.x_true)
    return Measurements(q=q, position=twin.true_positions(q), rotation=flange[..., :3, :3] @ PROBE)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A twin with its default errors and alpha4 off by 0.6 deg more, a model fitted to 150 noisy positions
    (orientation never measured), and 200 other poses measured with orientation."""
    twin = Twin.create(TwinConfig(seed=5, gear=False, gravity=False)).changed(alpha4=math.radians(0.25))
    gen = torch.Generator().manual_seed(5)
    train = twin.sample(150, gen)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = calibrate(twin.robot, train, prior=PriorSpec())
    stored = load_model(save_fit(tmp_path_factory.mktemp("replay") / "m", twin.robot, train, result, {}))
    # away from singular poses, where a position-first compensator gives up the orientation by design
    q = regular_poses(twin.robot, twin.robot.sample_joints(400, gen, margin=math.radians(20)))[:200]
    assert len(q) == 200
    return twin, stored, _measured(twin, q)


def test_the_replay_is_the_truth_at_the_commands_to_first_order(case):
    twin, stored, data = case
    commands = command_sets(stored, data.q)
    replayed = replay(stored, data, commands)
    for name, q_c in commands.items():
        truth = _measured(twin, q_c)
        true = errors_of_true_poses(stored, data, q_c, truth.rotation, truth.position)
        got = replayed[name]
        # second order: the model's motion over a correction dq differs from the robot's by the calibration's error
        # times dq (here below 3e-3 rad per rad of correction, 3e-5 m per rad); a replay that moved the measured
        # pose by the wrong motion would be off by the order of dq itself
        dq = got.largest_correction
        assert bool(((got.rotation_error - true.rotation_error).norm(dim=-1) <= 3e-3 * dq + 1e-12).all()), name
        assert bool(((got.position_error - true.position_error).norm(dim=-1) <= 3e-5 * dq + 1e-12).all()), name
        assert got.metrics()["orientation_rms_deg"] == pytest.approx(true.metrics()["orientation_rms_deg"], rel=0.02)


def _solved(stored, data: Measurements) -> Measurements:
    """The poses whose orientation the compensator reaches in its steps (the bounded wrist swing leaves a few
    poses near the wrist singularity short of it, as its residual output says)."""
    return data.subset(torch.nonzero(solved_mask(stored, data.q))[:, 0])


def test_the_compensator_leaves_what_the_model_misses_and_the_command_sets_differ_as_designed(case):
    _twin, stored, data = case
    data = _solved(stored, data)
    assert len(data) > 150
    commands = command_sets(stored, data.q, cap_deg=0.1)
    replayed = {k: v.metrics() for k, v in replay(stored, data, commands).items()}
    before, full = replayed["uncompensated"], replayed["compensator"]
    # the tilted wrist turns the tool by tenths of a degree; the position fit found it and the compensator removes it
    assert before["orientation_rms_deg"] > 0.3
    assert full["orientation_rms_deg"] < 0.2 * before["orientation_rms_deg"]
    assert full["position_rms_mm"] < 0.2 * before["position_rms_mm"]
    # position only: the position as well corrected, the orientation left, with smaller joint corrections
    only = replayed["position only"]
    assert only["position_rms_mm"] < 1.5 * full["position_rms_mm"] + 0.005
    assert only["orientation_rms_deg"] > 0.7 * before["orientation_rms_deg"]
    assert only["median_joint_correction_deg"] < full["median_joint_correction_deg"]
    # the cap holds and costs accuracy
    capped = replayed["capped at 0.1 deg"]
    assert capped["largest_joint_correction_deg"] <= 0.1 + 1e-9
    assert capped["orientation_rms_deg"] > full["orientation_rms_deg"]
    assert replayed["uncompensated"]["largest_joint_correction_deg"] == 0.0


def test_the_confirmed_share_is_one_for_a_right_change_and_zero_for_an_unrelated_one(case):
    _twin, stored, data = case
    data = _solved(stored, data)
    commands = command_sets(stored, data.q)
    replayed = replay(stored, data, commands)
    assert confirmed_share(replayed["uncompensated"], replayed["compensator"]) == pytest.approx(1.0, abs=0.1)
    # the same corrections handed to other poses: a change of the same size, unrelated to what each pose needs
    correction = commands["compensator"] - data.q
    shuffled = data.q + correction[torch.randperm(len(data), generator=torch.Generator().manual_seed(1))]
    unrelated = replay(stored, data, {"uncompensated": data.q, "shuffled": shuffled})
    assert abs(confirmed_share(unrelated["uncompensated"], unrelated["shuffled"])) < 0.3
    # commands that do not turn the tool have nothing to confirm
    with pytest.raises(ValueError, match="do not turn"):
        confirmed_share(unrelated["uncompensated"], unrelated["uncompensated"])


def test_replaying_no_poses_is_refused_by_the_metrics(case):
    _twin, stored, data = case
    empty = data.subset([])
    with pytest.raises(ValueError, match="no poses"):
        replay(stored, empty, {"uncompensated": empty.q})["uncompensated"].metrics()
