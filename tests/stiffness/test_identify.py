"""Stiffness identification on the loading-rig twin: truth recovery, identifiability, prediction."""

from __future__ import annotations

import pytest
import torch

from torchcal.core.errors import DataError, IdentifiabilityWarning, ModelError
from torchcal.kinematics import transforms as tf
from torchcal.stiffness.experiment import StiffnessData
from torchcal.stiffness.identify import (
    deflection_metrics,
    identify_stiffness,
    instrument_model,
    stiffness_regressor,
)
from torchcal.stiffness.vjm import compliance_from_stiffness, deflection, spring_names


def _truth(twin, names):
    return torch.stack([twin.joint_stiffness[int(n[3]) - 1] for n in names])


def _positions_only(data: StiffnessData) -> StiffnessData:
    return StiffnessData(q=data.q, wrench=data.wrench, deflection=data.deflection, unloaded=data.unloaded)


def test_classic_from_positions_recovers_observable_joints_and_names_the_rest(rig):
    twin, train, test = rig
    with pytest.warns(IdentifiabilityWarning, match=r"k_j6_rz \(no effect\)"):
        est = identify_stiffness(twin.robot, _positions_only(train))
    # The TCP lies on axis 6: its rotation cannot move the TCP, so positions cannot see it.
    assert est.identifiability.unobservable == ("k_j6_rz",)
    assert est.names == tuple(f"k_j{i}_rz" for i in range(1, 6))
    rel = est.stiffness / _truth(twin, est.names) - 1
    assert float(rel.abs().max()) < 0.10, rel
    # The reported uncertainty is honest: errors within 4 standard deviations.
    assert bool((rel.abs() < 4 * est.relative_std).all())
    assert 0.8 < est.sigma_ratio < 1.25
    metrics = deflection_metrics(est, test)
    assert metrics["n_poses"] == 200
    assert metrics["deflection_rms_mm"] <= 0.15 * metrics["deflection_measured_rms_mm"]
    # Noise floor: sqrt(2) * 0.012 mm per coordinate; the prediction error cannot beat it.
    assert metrics["deflection_rms_mm"] >= 0.9 * twin.noise_floor_mm()


def test_rotations_make_joint_six_observable(rig):
    twin, train, _ = rig
    est = identify_stiffness(twin.robot, train)
    assert est.with_rotation and est.identifiability.unobservable == ()
    rel = est.stiffness / _truth(twin, est.names) - 1
    assert len(est.names) == 6 and float(rel.abs().max()) < 0.10, rel
    assert est.observable() == est.names


def test_instrument_frame_is_registered_from_unloaded_points(rig):
    twin, train, _ = rig
    model, _ = instrument_model(twin.robot, train)
    T = model.T_reference
    assert float((T[:3, 3] - twin.T_instrument_base[:3, 3]).norm()) < 2e-5
    angle = tf.so3_log(T[:3, :3] @ twin.T_instrument_base[:3, :3].T).norm()
    assert float(angle) < 1e-5


def test_regressor_reproduces_the_vjm_deflection(rig, robot):
    _twin, train, _ = rig
    model, x = instrument_model(robot, train)
    gen = torch.Generator().manual_seed(4)
    stiffness = torch.exp(torch.rand(robot.dof, 6, generator=gen, dtype=torch.float64) * 3 + 11)
    names = spring_names(robot.dof)
    g = stiffness_regressor(model, train.q[:10], x, train.wrench[:10], names, with_rotation=True)
    dx = deflection(model, train.q[:10], x, compliance_from_stiffness(stiffness), train.wrench[:10])
    torch.testing.assert_close(g @ (1 / stiffness.reshape(-1)), dx, atol=1e-15, rtol=1e-10)


def test_full_diagonal_model_reports_structural_null_directions(rig):
    twin, train, test = rig
    with pytest.warns(IdentifiabilityWarning) as record:
        est = identify_stiffness(twin.robot, _positions_only(train), parameters="full")
    message = str(record[0].message)
    unobservable = set(est.identifiability.unobservable)
    # Structural facts of this arm: the TCP is on axis 6 (no effect of k_j6_rz); axes 2 and 3
    # are parallel, so translations along them cannot be told apart.
    assert "k_j6_rz" in unobservable and "k_j6_rz (no effect)" in message
    assert {"k_j2_tz", "k_j3_tz"} & unobservable
    assert len(est.names) + len(unobservable) == 36
    # The main axes' own springs survive and stay near the truth even in the larger model.
    by_name = est.stiffness_by_name()
    for i in (1, 2, 3):
        assert abs(by_name[f"k_j{i}_rz"] / float(twin.joint_stiffness[i - 1]) - 1) < 0.15
    metrics = deflection_metrics(est, test)
    assert metrics["deflection_rms_mm"] <= 0.15 * metrics["deflection_measured_rms_mm"]


def test_bad_requests_raise(rig, robot):
    _twin, train, _ = rig
    with pytest.raises(ModelError, match="k_j9_rz"):
        identify_stiffness(robot, train, parameters=["k_j9_rz"])
    with pytest.raises(ModelError, match="k_j1_qq"):
        identify_stiffness(robot, train, parameters=["k_j1_qq"])
    with pytest.raises(DataError, match="drx"):
        identify_stiffness(robot, _positions_only(train), use_rotation=True)
    short = StiffnessData(q=train.q[:, :5], wrench=train.wrench, deflection=train.deflection)
    with pytest.raises(DataError, match="6 joints"):
        identify_stiffness(robot, short)
    line = train.unloaded[:1] + torch.linspace(0, 1, 5, dtype=torch.float64)[:, None] * torch.tensor([1.0, 0.0, 0.0])
    collinear = StiffnessData(q=train.q[:5], wrench=train.wrench[:5], deflection=train.deflection[:5], unloaded=line)
    with pytest.raises(DataError, match="collinear"):
        identify_stiffness(robot, collinear)
