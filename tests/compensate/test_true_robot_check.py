"""The true-robot check of exported commands, on the geometric twin of the compensate fixtures."""

import math

import torch

from torchcal.compensate.graphs import build_graphs
from torchcal.compensate.production_tcp import production_view, tcp_transform
from torchcal.compensate.true_robot_check import compensation_on_true_robot
from torchcal.stages.store import load_model


def test_exported_commands_land_as_torch_commands_on_the_true_twin(exported, model_dir, twin):
    folder, manifest = exported
    flange = tcp_transform(None, None)  # the export's default TCP
    stored = production_view(load_model(model_dir), flange)
    q = twin.robot.sample_joints(300, torch.Generator().manual_seed(41), margin=math.radians(5))
    true_flange = lambda qq: twin.true_tcp_positions(qq, flange)  # noqa: E731
    result = compensation_on_true_robot(stored, build_graphs(stored), folder, manifest, q, true_flange)
    assert result["n_poses"] == 300
    # the acceptance: ONNX commands within 5 % of the torch compensator on the true robot
    assert result["onnx_float64_over_torch"] <= 1.05 and result["onnx_float32_over_torch"] <= 1.05
    # an independent recomputation of the torch number from the twin's truth
    T = stored.model.instrument_from_base(stored.x)
    target = stored.robot.tcp_position(q) @ T[:3, :3].T + T[:3, 3]
    with torch.no_grad():
        miss = (true_flange(build_graphs(stored)["compensator"](q)) - target).norm(dim=-1)
    assert abs(float(miss.pow(2).mean().sqrt()) * 1e3 - result["torch"]["position_rms_mm"]) < 1e-9
    # where the Newton steps solved the model, only the calibration's own error remains: far
    # below the uncompensated error, and the unsolved poses are the minority
    assert result["solved_share"] > 0.8
    # at the flange, what compensation leaves is the model's own error there (true minus monitor-predicted)
    own = result["model_own_error"]["position_rms_mm"]
    assert result["torch_on_solved"]["position_rms_mm"] <= 1.10 * own
    assert result["torch_on_solved"]["position_rms_mm"] < 0.5 * result["uncompensated"]["position_rms_mm"]
    assert result["torch_on_solved"]["n_poses"] + (result["torch_on_unsolved"] or {"n_poses": 0})["n_poses"] == 300
