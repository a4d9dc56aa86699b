"""Export of a model folder with a stiffness stage: wrench input, parity with onnxruntime, the twin."""

import hashlib
import json
import math

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from torchcal.compensate.compensator import CompensatorWithResidual
from torchcal.compensate.export import RESIDUAL_OUTPUT, export_model
from torchcal.compensate.export_checks import sample_wrenches
from torchcal.compensate.graphs import GRAPHS, WRENCH_INPUT, build_graphs, onnx_bytes
from torchcal.compensate.production_tcp import production_view, tcp_transform
from torchcal.compensate.runtime import CompensatorError, CompensatorRuntime
from torchcal.instruments.stiffness.commands import fit_stiffness
from torchcal.instruments.stiffness.twin import StiffnessTwin
from torchcal.instruments.stiffness.twin_case import StiffnessCaseConfig, write_stiffness_twin_case
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.stages.store import load_model

CASE = StiffnessCaseConfig(seed=12, n_train=80, n_test=10)


@pytest.fixture(scope="module")
def stiff_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("stiff")
    paths = write_stiffness_twin_case(root / "case", CASE)
    return fit_stiffness(paths["robot.yaml"], paths["stiffness_train.csv"], root / "model", []).folder


@pytest.fixture(scope="module")
def stiff_export(stiff_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("stiff_export")
    # the production TCP is where the twin's load acts and where it is scored: its tool point
    tool_mm = (load_model(stiff_dir).robot.tool * 1e3).tolist()
    return out, export_model(stiff_dir, out, tcp_mm=tool_mm)


@pytest.fixture(scope="module")
def stored(stiff_dir):
    """The model as the exported files serve it: the production TCP at the tool point (``stiff_export``)."""
    stored = load_model(stiff_dir)
    return production_view(stored, tcp_transform((stored.robot.tool * 1e3).tolist(), None))


@pytest.fixture(scope="module")
def graphs(stored):
    return build_graphs(stored)


def run(folder, key, q, wrench):
    name, dtype, input_name, _ = GRAPHS[key]
    session = ort.InferenceSession(str(folder / name), providers=["CPUExecutionProvider"])
    feeds = {input_name: q.to(dtype).numpy(), "wrench": wrench.to(dtype).numpy()}
    return torch.from_numpy(session.run(None, feeds)[0]).double()


def loads(n, seed):
    return sample_wrenches(n, 300.0, 30.0, torch.Generator().manual_seed(seed))


def test_manifest_documents_the_wrench_input(stiff_export, stiff_dir):
    folder, manifest = stiff_export
    assert json.loads((folder / "manifest.json").read_text()) == manifest
    assert manifest["stages"] == {"geometry": True, "residual": False, "stiffness": True, "gravity_compliance": False, "joint_harmonics": False}
    wrench = manifest["wrench"]
    assert wrench["name"] == "wrench" and wrench["frame"] == "tool" and wrench["shape"] == "(batch, 6)"
    assert wrench["components"] == ["fx", "fy", "fz", "tx", "ty", "tz"] and wrench["units"] == ["N"] * 3 + ["N m"] * 3
    assert manifest["extra_inputs"] == {"compensator": ["wrench"], "monitor": ["wrench"]}
    stiffness = json.loads((stiff_dir / "stiffness.json").read_text())
    assert manifest["stiffness"]["entries"] == {n: p["value"] for n, p in stiffness["parameters"].items()}
    assert "wrench" in (folder / "README.md").read_text()
    for key, name in manifest["files"].items():
        data = (folder / name).read_bytes()
        assert hashlib.sha256(data).hexdigest() == manifest["sha256"][key]
        model = onnx.load_from_string(data)
        onnx.checker.check_model(model)
        inputs = [(i.name, [d.dim_param or d.dim_value for d in i.type.tensor_type.shape.dim]) for i in model.graph.input]
        assert inputs == [(GRAPHS[key][2], ["batch", 6]), ("wrench", ["batch", 6])]
        # the compensator's two phases of steps are Loops (their bodies hold the deflection), the monitor has none
        loops = [n.op_type for n in model.graph.node if n.op_type in ("Loop", "Scan", "If")]
        assert loops == (["Loop", "Loop"] if key.startswith("compensator") else [])
        bodies = [a.g for n in model.graph.node for a in n.attribute if a.type == onnx.AttributeProto.GRAPH]
        assert not any(n.op_type == "If" for g in [model.graph, *bodies] for n in g.node)


def test_monitor_parity_with_wrench_on_10k_poses(stiff_export, stored, graphs):
    folder, _ = stiff_export
    q = stored.robot.sample_joints(10_000, torch.Generator().manual_seed(61))
    w = loads(10_000, 62)
    with torch.no_grad():
        ref = graphs["monitor"](q, w)
        unloaded = graphs["monitor"](q, torch.zeros_like(w))
    assert float((ref - unloaded).norm(dim=-1).median()) > 1e-4  # the wrench matters (> 0.1 mm)
    assert (run(folder, "monitor", q, w) - ref).norm(dim=-1).max() * 1e3 <= 1e-9  # mm
    assert (run(folder, "monitor_f32", q, w) - ref).norm(dim=-1).max() * 1e3 <= 1e-3


def test_compensator_parity_with_wrench_on_10k_poses(stiff_export, stored, graphs):
    """As the geometric parity test: commands compared through the calibrated FK (TCP, mm)."""
    folder, _ = stiff_export
    q = stored.robot.sample_joints(10_000, torch.Generator().manual_seed(63))
    w = loads(10_000, 64)
    with torch.no_grad():
        ref = graphs["compensator"](q, w)
    model = stored.model
    tcp = lambda qq: (model.base_flange_pose(qq, stored.x) @ model.flange_from_tool(stored.x))[..., :3, 3]  # noqa: E731
    _, jac = geometric_jacobian(ErrorModel(stored.robot), q, stored.x)
    regular = torch.linalg.svdvals(jac)[:, -1] > 0.01
    assert regular.double().mean() > 0.8
    d64 = (tcp(run(folder, "compensator", q, w)) - tcp(ref)).norm(dim=-1) * 1e3
    assert d64[regular].max() <= 1e-9 and d64.max() <= 1e-6
    d32 = (tcp(run(folder, "compensator_f32", q, w)) - tcp(ref)).norm(dim=-1) * 1e3
    assert d32[regular].median() <= 1e-4


def test_float32_compensator_is_finite_at_the_wrist_singularity(stiff_export, stored):
    folder, manifest = stiff_export
    q = stored.robot.sample_joints(5_000, torch.Generator().manual_seed(68))
    q[:, 4] = (torch.rand(5_000, generator=torch.Generator().manual_seed(69), dtype=torch.float64) - 0.5) * 2e-3
    out = run(folder, "compensator_f32", q, loads(5_000, 70))
    assert bool(torch.isfinite(out).all())
    assert (out - q).abs().max() < 0.5  # bounded correction, rad
    budget = manifest["float32_error_budget"]
    assert all(math.isfinite(v) for v in budget["compensator_tcp_mm"].values())


def test_runtime_with_wrench(stiff_export, graphs, stored, exported):
    rt = CompensatorRuntime(stiff_export[0])
    q = stored.robot.sample_joints(20, torch.Generator().manual_seed(65))
    w = loads(20, 66)
    with torch.no_grad():
        ref = graphs["compensator"](q, w).numpy()
        ref_one = graphs["compensator"](q, w[:1].expand(20, 6)).numpy()
    np.testing.assert_allclose(rt.correct(q.numpy(), w.numpy()), ref, atol=1e-12)
    np.testing.assert_allclose(rt.correct(q[0].numpy(), w[0].numpy()), ref[0], atol=1e-12)
    np.testing.assert_allclose(rt.correct(q.numpy(), w[0].numpy()), ref_one, atol=1e-12)  # one load for a batch
    assert rt.predict_error(q.numpy(), w.numpy()).shape == (20, 3)
    with pytest.raises(CompensatorError, match="wrench"):
        rt.correct(q.numpy())
    with pytest.raises(CompensatorError, match="wrench has shape"):
        rt.correct(q.numpy(), np.zeros((3, 6)))
    bad = w.numpy().copy()
    bad[2, 4] = np.nan
    with pytest.raises(CompensatorError, match="NaN"):
        rt.correct(q.numpy(), bad)
    with pytest.raises(CompensatorError, match="no stiffness stage"):
        CompensatorRuntime(exported[0]).correct(q.numpy(), w.numpy())


def test_exported_compensation_on_the_loaded_twin(stiff_export):
    """Commands from the ORT runner sent to the true loaded robot: the TCP error the load causes
    (exact deformed chain, spring equilibrium on the deflected structure) drops by >= 80 %."""
    twin = StiffnessTwin(CASE.twin_config())
    gen = torch.Generator().manual_seed(67)
    q = twin.sample_poses(300, gen)
    w = twin.sample_wrenches(300, gen)
    rt = CompensatorRuntime(stiff_export[0])
    target = twin.unloaded_pose(q)  # the twin's geometry is the nominal one: the nominal target

    def errors(qq):
        loaded = twin.loaded_pose(qq, w)
        dp = (loaded[:, :3, 3] - target[:, :3, 3]).norm(dim=-1) * 1e3
        dr = (loaded[:, :3, :3] @ target[:, :3, :3].transpose(-1, -2) - torch.eye(3, dtype=torch.float64)).abs().amax((-1, -2))
        return float(dp.pow(2).mean().sqrt()), float(dr.max())

    before = errors(q)
    for precision in ("float64", "float32"):
        q_c = torch.from_numpy(CompensatorRuntime(stiff_export[0], precision=precision).correct(q.numpy(), w.numpy())).double()
        after = errors(q_c)
        assert after[0] <= 0.2 * before[0], precision
        assert after[1] <= 0.2 * before[1], precision
    assert before[0] > 0.2  # mm: a real load
    assert rt.manifest["stages"]["stiffness"]


def test_loaded_float32_file_computes_what_the_traced_float32_graph_computes(stiff_export, stored, graphs):
    """With the wrench input too, the float32 file (the float64 one behind casts) gives the traced
    float32 graph's bits."""
    folder, _ = stiff_export
    traced = onnx_bytes(CompensatorWithResidual(graphs["compensator_f32"]), stored.robot.dof, torch.float32, "q_nominal",
                        "q_corrected", wrench_input=WRENCH_INPUT, extra_outputs=(RESIDUAL_OUTPUT,))
    q = stored.robot.sample_joints(2000, torch.Generator().manual_seed(31))
    feeds = {"q_nominal": q.float().numpy(), WRENCH_INPUT: loads(2000, 32).float().numpy()}
    exported = ort.InferenceSession(str(folder / GRAPHS["compensator_f32"][0]), providers=["CPUExecutionProvider"])
    theirs = ort.InferenceSession(traced, providers=["CPUExecutionProvider"]).run(None, feeds)
    for mine, reference in zip(exported.run(None, feeds), theirs, strict=True):
        assert mine.dtype == np.float32
        np.testing.assert_array_equal(mine, reference)
