"""A model folder's optional stages: read through one table, seen as typed views, never aliased by a view."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch

from torchcal.compensate.production_tcp import production_view, tcp_transform
from torchcal.identify.calibrate import calibrate
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.base import GeometryStage, ResidualStage, StiffnessStage
from torchcal.stages.geometry import save_fit
from torchcal.stages.store import OPTIONAL_STAGES, load_model


def test_optional_stages_are_parts_and_a_view_does_not_share_their_edits(tmp_path):
    twin = Twin.create(TwinConfig(seed=11))
    train = twin.sample(60, torch.Generator().manual_seed(5))
    stored = load_model(save_fit(tmp_path / "model", twin.robot, train, calibrate(twin.robot, train), {}))
    assert stored.parts == {} and stored.residual is None and stored.stiffness is None
    assert [type(s) for s in stored.stages()] == [GeometryStage]
    assert list(OPTIONAL_STAGES) == ["residual", "stiffness"]  # the order a prediction applies them

    from types import SimpleNamespace

    # a stand-in part: the stage list needs it to exist and to take the robot's joints
    head = SimpleNamespace(features=SimpleNamespace(mid=torch.zeros(twin.robot.dof)))
    stored.residual = head
    assert stored.parts == {"residual": head} and stored.residual is head
    assert [type(s) for s in stored.stages()] == [GeometryStage, ResidualStage]
    view = production_view(stored, tcp_transform([0.0, 0.0, 50.0], None))
    assert view.residual is head
    view.residual = None  # an edit of the view leaves the model it came from alone
    assert stored.residual is head and view.residual is None
    assert [type(s) for s in view.stages()] == [GeometryStage]
    # each stage is bound to the chain of the object it came from, not to a copy made earlier
    assert view.stages()[0].model is view.model and stored.stages()[0].model is stored.model
    other = replace(stored, x=stored.x.clone())
    other.stiffness = None  # absent stays absent, and the original keeps its head
    assert stored.residual is head and StiffnessStage not in [type(s) for s in other.stages()]


def test_calibrated_yaml_of_a_urdf_robot_puts_the_tcp_where_the_model_does(tmp_path):
    """A URDF's fixed frame N -> flange has no field in the contract's YAML: it is folded into the tool
    point, so the written table and tool give the model's TCP (up to the fixed base -> frame 0, which the
    header names). It was dropped: the TCP came out 0.38 mm off on a Panda."""
    from torchcal.data.measurements import Measurements
    from torchcal.kinematics.error_model import ErrorModel
    from torchcal.kinematics.robot import load_robot

    urdf = Path(__file__).parents[1] / "kinematics" / "fixtures" / "arm6_offset.urdf"
    robot = replace(load_robot(urdf), tool=torch.tensor([0.01, -0.02, 0.1], dtype=torch.float64))
    assert not torch.allclose(robot.T_n_flange, torch.eye(4, dtype=torch.float64))
    q = robot.sample_joints(80, torch.Generator().manual_seed(1))
    data = Measurements(q=q, position=robot.tcp_position(q))
    result = calibrate(robot, data)
    folder = save_fit(tmp_path / "model", robot, data, result, {})
    written = load_robot(folder / "calibrated_robot.yaml")
    check = robot.sample_joints(50, torch.Generator().manual_seed(2))
    model = ErrorModel(robot)  # the model's TCP in MDH frame 0: the base transform taken out
    tcp_base = (model.base_flange_pose(check, result.x) @ model.flange_from_tool(result.x))[:, :3, 3]
    t0 = robot.T_base_0.to(torch.float64)
    tcp_frame0 = (tcp_base - t0[:3, 3]) @ t0[:3, :3]
    assert float((written.tcp_position(check) - tcp_frame0).norm(dim=-1).max()) < 1e-9  # m
    assert "folded into the tool point" in (folder / "calibrated_robot.yaml").read_text().replace("\n# ", " ")
