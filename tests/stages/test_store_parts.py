"""A model folder's optional stages: read through one table, seen as typed views, never aliased by a view."""

from __future__ import annotations

from dataclasses import replace

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
