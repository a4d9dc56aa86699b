"""Exported ONNX files against the torch graphs, the manifest, and the twin."""

import hashlib
import json
import math

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from torchcal.compensate.compensator import CompensatorWithResidual
from torchcal.compensate.export import RESIDUAL_OUTPUT, export_and_check
from torchcal.compensate.export_checks import wrist_singular_samples
from torchcal.compensate.graphs import GRAPHS, OPSET, build_graphs, onnx_bytes
from torchcal.compensate.production_tcp import production_view, tcp_transform
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.stages.store import load_model


@pytest.fixture(scope="module")
def stored(model_dir):
    """The model as the exported files serve it: the default production TCP, the flange."""
    return production_view(load_model(model_dir), tcp_transform(None, None))


@pytest.fixture(scope="module")
def graphs(stored):
    return build_graphs(stored)


def session(path):
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def run(folder, key, q: torch.Tensor, loaded: ort.InferenceSession | None = None) -> torch.Tensor:
    """Graph ``key`` of the export in ``folder`` on ``q``, in a new session or the ``loaded`` one."""
    name, dtype, input_name, _ = GRAPHS[key]
    loaded = loaded or session(folder / name)
    return torch.from_numpy(loaded.run(None, {input_name: q.to(dtype).numpy()})[0]).double()


def test_manifest_describes_the_files(exported, model_dir, stored):
    folder, manifest = exported
    assert json.loads((folder / "manifest.json").read_text()) == manifest
    assert manifest["robot"] == stored.robot.name
    assert manifest["joint_names"] == list(stored.robot.joint_names)
    assert manifest["stages"] == {"geometry": True, "residual": False, "stiffness": False, "gravity_compliance": False, "joint_harmonics": False}
    assert manifest["opset"] == OPSET
    assert manifest["training_data"]["sha256"] == json.loads((model_dir / "calibration.json").read_text())["data"]["sha256"]
    assert "rad" in manifest["units"]["compensator"]["input"] and "rad" in manifest["units"]["compensator"]["output"]
    for key, name in manifest["files"].items():
        data = (folder / name).read_bytes()
        assert hashlib.sha256(data).hexdigest() == manifest["sha256"][key]
        model = onnx.load_from_string(data)
        onnx.checker.check_model(model)
        assert model.opset_import[0].version == OPSET
        assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in model.graph.initializer)
        loops = [n for n in model.graph.node if n.op_type in ("Loop", "Scan", "If")]
        # the compensator's two phases of steps (mixed, then position-only) are Loops; the monitor has none
        assert [n.op_type for n in loops] == (["Loop", "Loop"] if key.startswith("compensator") else [])
    readme = (folder / "README.md").read_text()
    assert readme.count("rad") >= 2
    # the corrections the integrator should expect, and which figure the limits judge (the manifest's keys say it too)
    largest = manifest["corrections"]["extent"]["training poses"]["largest_joint_correction_deg"]
    assert f"largest {largest:.3g} deg" in readme and "judged on the median over the training poses" in readme
    assert set(manifest["corrections"]["limits"]) >= {"median_joint_correction_deg", "median_tool_rotation_deg", "judged"}
    for v in ("torchcal", "torch", "onnx", "onnxruntime"):
        assert manifest["versions"][v]
    assert manifest["float32_error_budget"]["monitor_mm"]["max"] < 1e-3


def test_monitor_parity_on_10k_poses(exported, stored, graphs):
    folder, _ = exported
    q = stored.robot.sample_joints(10_000, torch.Generator().manual_seed(21))
    with torch.no_grad():
        ref = graphs["monitor"](q)
    assert (run(folder, "monitor", q) - ref).norm(dim=-1).max() * 1e3 <= 1e-9  # mm
    assert (run(folder, "monitor_f32", q) - ref).norm(dim=-1).max() * 1e3 <= 1e-3  # mm


def test_float32_file_computes_what_the_traced_float32_graph_computes(exported, stored, graphs):
    """The float32 compensator is the float64 file behind cast inputs and outputs: the same bits, on
    uniform and wrist-singular poses, as the float32 graph traced from its own parts."""
    folder, _ = exported
    traced = onnx_bytes(CompensatorWithResidual(graphs["compensator_f32"]), stored.robot.dof, torch.float32, "q_nominal",
                        "q_corrected", extra_outputs=(RESIDUAL_OUTPUT,))
    gen = torch.Generator().manual_seed(24)
    q = torch.cat([stored.robot.sample_joints(3000, gen), wrist_singular_samples(stored.robot, 1000, gen)]).float().numpy()
    exported_outputs = session(folder / GRAPHS["compensator_f32"][0]).run(None, {"q_nominal": q})
    traced_outputs = ort.InferenceSession(traced, providers=["CPUExecutionProvider"]).run(None, {"q_nominal": q})
    assert [o.dtype for o in exported_outputs] == [np.float32, np.float32]
    for mine, theirs in zip(exported_outputs, traced_outputs, strict=True):
        np.testing.assert_array_equal(mine, theirs)


def test_compensator_parity_on_10k_poses(exported, stored, graphs):
    """Commands compared through the calibrated FK (TCP mm).

    float64 is bounded where the Jacobian's smallest singular value exceeds 0.01 (about 88 % of
    uniform poses): closer to a singularity rounding differences of the damped step are amplified
    by 1/sigma (max over all poses ~1e-9 mm). float32 is bounded where the fixed iteration count
    has converged (float64 residual below 1e-9 m, > 80 % of uniform poses); where it has not
    (near singularities) the partial iterate itself is rounding-sensitive (measured over all poses
    with the float64 solve, default run's model: p99 ~2e-4 mm, max ~5e-3 mm; every export's manifest
    reports its own).
    """
    folder, _ = exported
    q = stored.robot.sample_joints(10_000, torch.Generator().manual_seed(22))
    with torch.no_grad():
        ref = graphs["compensator"](q)
    model = stored.model
    tcp = lambda qq: (model.base_flange_pose(qq, stored.x) @ model.flange_from_tool(stored.x))[..., :3, 3]  # noqa: E731
    _, jac = geometric_jacobian(ErrorModel(stored.robot), q, stored.x)
    regular = torch.linalg.svdvals(jac)[:, -1] > 0.01
    assert regular.double().mean() > 0.8
    d64 = (tcp(run(folder, "compensator", q)) - tcp(ref)).norm(dim=-1) * 1e3
    assert d64[regular].max() <= 1e-9 and d64.max() <= 1e-6
    target = stored.robot.tcp_position(q)
    converged = (tcp(ref) - target).norm(dim=-1) < 1e-9
    assert converged.double().mean() > 0.8
    d32 = (tcp(run(folder, "compensator_f32", q)) - tcp(ref)).norm(dim=-1) * 1e3
    assert d32[converged].max() <= 1e-3


def test_onnx_compensation_on_the_true_twin(exported, twin, stored, graphs):
    """Corrected joints sent to the true robot put its flange (the default TCP) on T_reference @ nominal flange."""
    folder, manifest = exported
    assert manifest["tcp"]["is_flange"] and manifest["tcp"]["position_mm"] == [0.0, 0.0, 0.0]
    q = twin.robot.sample_joints(400, torch.Generator().manual_seed(23), margin=math.radians(5))
    base = stored.model.instrument_from_base(stored.x)
    target = twin.robot.flange_pose(q)[..., :3, 3] @ base[:3, :3].T + base[:3, 3]
    flange = torch.eye(4, dtype=torch.float64)
    rms = lambda qq: float((twin.true_tcp_positions(qq, flange) - target).norm(dim=-1).pow(2).mean().sqrt() * 1e3)  # noqa: E731
    with torch.no_grad():
        torch_rms = rms(graphs["compensator"](q))
    onnx_rms = rms(run(folder, "compensator", q))
    onnx32_rms = rms(run(folder, "compensator_f32", q))
    uncompensated = rms(q)
    assert onnx_rms <= 1.05 * torch_rms and onnx32_rms <= 1.05 * torch_rms
    # the flange is not the measured point: what compensation leaves there is the model's own error at
    # the flange (true minus predicted at the same joints), not the tracker's noise
    with torch.no_grad():
        predicted = stored.model.tcp_position(q, stored.x)
    own = float((twin.true_tcp_positions(q, flange) - predicted).norm(dim=-1).pow(2).mean().sqrt() * 1e3)
    assert onnx_rms <= 1.10 * own
    assert onnx_rms < 0.5 * uncompensated


def test_export_and_check_reports_parity(model_dir, twin, tmp_path):
    gen = torch.Generator().manual_seed(24)
    test = twin.sample(200, gen)
    result = export_and_check(model_dir, tmp_path / "out", test, true_tcp_positions=twin.true_tcp_positions)
    assert result["compensator_tcp_max_mm"] <= 1e-9
    on_twin = result["compensation_on_true_robot"]  # the exported commands sent to the true twin
    assert on_twin["n_poses"] == 200 and on_twin["onnx_float64_over_torch"] <= 1.05
    # scored at the exported TCP (the flange): what is left is the model's own error there
    assert on_twin["torch"]["position_rms_mm"] <= 1.10 * on_twin["model_own_error"]["position_rms_mm"]
    assert on_twin["torch"]["position_rms_mm"] < 0.5 * on_twin["uncompensated"]["position_rms_mm"]
    assert result["monitor_max_mm"] <= 1e-9
    assert result["n_poses"] == 200
    # the exported monitor predicts the held-out tracker points to the noise level of the twin (an
    # in-model twin: no gravity, no gear errors; 150 training poses leave a few percent above the floor)
    assert result["held_out_monitor"]["position_rms_mm"] < 1.2 * twin.config.noise_floor_rms_mm
    assert (tmp_path / "out" / "manifest.json").is_file()


def test_exported_loops_give_a_pose_the_same_command_alone_and_in_a_batch(exported, stored, graphs):
    """The Loops step until every pose of the batch has converged; a converged pose keeps its
    command meanwhile, so its result is the one it gets alone (and torch's)."""
    folder, _ = exported
    q = stored.robot.sample_joints(40, torch.Generator().manual_seed(25))
    q[:5, -2] = 0.0  # wrist-singular poses take more steps than the rest
    together = run(folder, "compensator", q)
    # each pose alone: a batch of one through a session of the same file (one session for the
    # forty, as a controller keeps its session; a session is opened in about 0.1 s)
    loaded = session(folder / GRAPHS["compensator"][0])
    alone = torch.cat([run(folder, "compensator", row[None], loaded) for row in q])
    assert (together - alone).abs().max() < 1e-12  # rad
    with torch.no_grad():
        assert (together - graphs["compensator"](q)).abs().max() < 1e-9


def test_export_with_a_tool_length_states_it_and_the_default_warns_of_turned_tools(model_dir, exported, tmp_path, capsys):
    from torchcal.cli import main

    # the default export (position first, the TCP alone judged): its convergence report counts the turned tools
    _, manifest = exported
    uniform = manifest["convergence"]["strata"]["uniform"]
    assert uniform["share_tool_turn_added_above_1_deg"] > 0 and manifest["solver"]["tool_length_m"] == 0.0
    assert main(["export", "--model", str(model_dir), "--out", str(tmp_path / "held")]) == 0
    assert "turn the tool more than 1 deg beyond the nominal command" in capsys.readouterr().out
    assert main(["export", "--model", str(model_dir), "--out", str(tmp_path / "guarded"), "--tool-length-mm", "100"]) == 0
    assert "turn the tool" not in capsys.readouterr().out
    guarded = json.loads((tmp_path / "guarded" / "manifest.json").read_text())
    assert guarded["solver"]["tool_length_m"] == pytest.approx(0.1)
    assert "Exported with a tool length of 100 mm" in (tmp_path / "guarded" / "README.md").read_text()
    added = guarded["convergence"]["strata"]["uniform"]["tool_turn_added_rad"]["max"]
    assert added < uniform["tool_turn_added_rad"]["max"]  # kept nominal where the turn would cost a tool its position
    assert main(["export", "--model", str(model_dir), "--out", str(tmp_path / "bad"), "--tool-length-mm", "-5"]) == 2
    assert "--tool-length-mm must be a finite length >= 0 mm" in capsys.readouterr().err


def test_portable_export_uses_standard_operators_only_and_reaches_the_same_targets(model_dir, exported, stored, tmp_path):
    """``--portable``: no onnxruntime contrib node anywhere (Loop bodies included), and the
    commands put the calibrated TCP on the nominal target as the default export's do."""
    from torchcal.compensate.compensator import CONVERGED_POSITION_M
    from torchcal.compensate.export import export_model
    from torchcal.compensate.linalg import CONTRIB_DOMAIN

    folder, _ = exported
    manifest = export_model(model_dir, tmp_path / "portable", portable=True)

    def domains(graph) -> set[str]:
        found = {node.domain for node in graph.node}
        for node in graph.node:
            for attribute in node.attribute:
                if attribute.type == onnx.AttributeProto.GRAPH:
                    found |= domains(attribute.g)
        return found

    for key in ("compensator", "compensator_f32"):
        model = onnx.load(str(tmp_path / "portable" / manifest["files"][key]))
        assert CONTRIB_DOMAIN not in domains(model.graph) | {o.domain for o in model.opset_import}
    default_model = onnx.load(str(folder / GRAPHS["compensator"][0]))
    assert CONTRIB_DOMAIN in domains(default_model.graph)  # the default does use onnxruntime's Inverse
    gen = torch.Generator().manual_seed(31)
    q = torch.cat([stored.robot.sample_joints(1000, gen), wrist_singular_samples(stored.robot, 300, gen)])
    model = stored.model
    tcp = lambda qq: (model.base_flange_pose(qq, stored.x) @ model.flange_from_tool(stored.x))[..., :3, 3]  # noqa: E731
    target = stored.robot.tcp_position(q)
    left_default = (tcp(run(folder, "compensator", q)) - target).norm(dim=-1)
    left_portable = (tcp(run(tmp_path / "portable", "compensator", q)) - target).norm(dim=-1)
    solved = left_default < CONVERGED_POSITION_M
    assert solved.double().mean() > 0.9
    assert float(left_portable[solved].max()) < 2 * CONVERGED_POSITION_M
    assert (left_portable < CONVERGED_POSITION_M).double().mean() >= solved.double().mean() - 0.01
