"""The controller-side runtime: integrity and input checks, and no torch."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchcal.compensate.graphs import build_graphs
from torchcal.compensate.production_tcp import production_view, tcp_transform
from torchcal.compensate.runtime import CompensatorError, CompensatorRuntime
from torchcal.core.errors import TorchcalError
from torchcal.stages.store import load_model

ROOT = Path(__file__).resolve().parents[2]


def write_manifest(folder: Path, manifest) -> None:
    """Write ``manifest`` into ``folder`` with its SHA-256 recorded in ``checksums.json``, as an export does:
    a manifest the runner must judge by its content, not by a checksum mismatch."""
    import hashlib
    import json

    data = json.dumps(manifest).encode()
    (folder / "manifest.json").write_bytes(data)
    path = folder / "checksums.json"
    checksums = json.loads(path.read_text()) if path.is_file() else {"format": "torchcal-checksums/1", "files": {}}
    checksums["files"]["manifest.json"] = hashlib.sha256(data).hexdigest()
    path.write_text(json.dumps(checksums))


@pytest.fixture()
def folder(exported, tmp_path):
    copy = tmp_path / "exported"
    shutil.copytree(exported[0], copy)
    return copy


def test_runtime_matches_torch(exported, model_dir):
    rt = CompensatorRuntime(exported[0])
    stored = load_model(model_dir)
    graphs = build_graphs(production_view(stored, tcp_transform(None, None)))  # the export's default TCP: the flange
    q = stored.robot.sample_joints(50, torch.Generator().manual_seed(31))
    with torch.no_grad():
        ref = graphs["compensator"](q).numpy()
    np.testing.assert_allclose(rt.correct(q.numpy()), ref, atol=1e-12)
    np.testing.assert_allclose(rt.correct(q[0].numpy()), ref[0], atol=1e-12)  # single pose
    assert rt.predict_error(q.numpy()).shape == (50, 3)
    rt32 = CompensatorRuntime(exported[0], precision="float32", threads=1)
    assert rt32.correct(q.numpy()).dtype == np.float32


def test_correct_one_is_correct_with_residual_on_bound_buffers(exported, model_dir):
    """The per-cycle path returns what the checked batch path does, call after call (its buffers
    are reused: each result must be a copy), and checks its input the same way."""
    rt = CompensatorRuntime(exported[0])
    q = load_model(model_dir).robot.sample_joints(20, torch.Generator().manual_seed(32)).numpy()
    expected_q, expected_residual = rt.correct_with_residual(q)
    got = [rt.correct_one(row) for row in q]
    np.testing.assert_array_equal(np.stack([g[0] for g in got]), expected_q)
    np.testing.assert_array_equal(np.stack([g[1] for g in got]), expected_residual)
    with pytest.raises(CompensatorError, match="expected \\(6,\\)"):
        rt.correct_one(q[:2])
    with pytest.raises(CompensatorError, match="NaN"):
        rt.correct_one(np.full(6, np.nan))


def test_tampered_file_is_refused(folder):
    path = folder / "compensator.onnx"
    data = bytearray(path.read_bytes())
    data[-1] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(CompensatorError, match="SHA-256"):
        CompensatorRuntime(folder)


def test_bad_inputs_are_refused(exported):
    rt = CompensatorRuntime(exported[0])
    with pytest.raises(CompensatorError, match="expected \\(6,\\)"):
        rt.correct(np.zeros((3, 5)))
    q = np.zeros((2, 6))
    q[1, 2] = np.nan
    with pytest.raises(CompensatorError, match="NaN") as info:
        rt.correct(q)
    assert isinstance(info.value, TorchcalError)
    with pytest.raises(CompensatorError, match="NaN"):
        rt.predict_error(np.full(6, np.inf))


def test_mismatched_model_is_refused(exported, folder):
    with pytest.raises(CompensatorError, match="not 'kr16'"):
        CompensatorRuntime(exported[0], expected_robot="kr16")
    with pytest.raises(CompensatorError, match="do not match"):
        CompensatorRuntime(exported[0], expected_joints=["a1", "a2", "a3", "a4", "a5", "a6"])
    # a manifest that claims another joint count than the graph has
    import json

    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["n_joints"], manifest["joint_names"], manifest["joint_limits_rad"] = 7, [*manifest["joint_names"], "j7"], None
    write_manifest(folder, manifest)
    with pytest.raises(CompensatorError, match="7 joints"):
        CompensatorRuntime(folder)


def test_controller_demo_runs_without_torch(exported):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "controller_demo.py"), str(exported[0])],
        capture_output=True, text=True, timeout=60, cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr
    assert "torch imported: False" in proc.stdout
    assert proc.stdout.count("correction") == 5


def test_runtime_module_does_not_import_torch():
    code = "import sys; import torchcal.compensate.runtime; print('torch' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT,
                          env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"


def test_float32_graph_is_finite_and_close_to_float64_at_singular_wrist_poses(exported, model_dir):
    """The float32 graphs solve their 6x6 systems in float64: at |q5| < 1e-3 rad (100 poses exactly
    0) every command is finite and puts the calibrated TCP where the float64 command does."""
    folder, _ = exported
    stored = load_model(model_dir)
    gen = torch.Generator().manual_seed(5)
    q = torch.clamp((torch.rand(2000, 6, generator=gen, dtype=torch.float64) - 0.5) * 2.0,
                    *stored.robot.joint_limits.T)  # within the limits (the runner refuses joints beyond them)
    q[:, 4] = (torch.rand(2000, generator=gen, dtype=torch.float64) - 0.5) * 2e-3
    q[:100, 4] = 0.0
    q = q.float().double()  # both precisions see the same joints
    q32 = CompensatorRuntime(folder, precision="float32").correct(q.numpy())  # refuses non-finite rows
    q64 = CompensatorRuntime(folder).correct(q.numpy())
    tcp = lambda qq: (stored.model.base_flange_pose(qq, stored.x) @ stored.model.flange_from_tool(stored.x))[..., :3, 3]  # noqa: E731
    gap_mm = (tcp(torch.from_numpy(q32).double()) - tcp(torch.from_numpy(q64))).norm(dim=-1) * 1e3
    assert float(gap_mm.max()) <= 1e-3


def _nan_folder(tmp_path: Path) -> Path:
    """An exported folder whose tiny compensator (hashes in the manifest match) returns
    ``q + log(w)``: NaN on the rows where the second input ``w`` (the wrench slot) is negative."""
    import hashlib

    from onnx import TensorProto, helper

    def graph(name: str, width: int) -> bytes:
        nodes = [helper.make_node("Log", ["sign"], ["log"]), helper.make_node("Add", ["q", "log"], ["sum"]),
                 helper.make_node("Slice", ["sum", "s0", "s1", "ax"], ["out"])]
        inits = [helper.make_tensor("s0", TensorProto.INT64, [1], [0]), helper.make_tensor("s1", TensorProto.INT64, [1], [width]),
                 helper.make_tensor("ax", TensorProto.INT64, [1], [1])]
        g = helper.make_graph(nodes, name, [helper.make_tensor_value_info("q", TensorProto.DOUBLE, ["batch", 6]),
                                            helper.make_tensor_value_info("sign", TensorProto.DOUBLE, ["batch", 6])],
                              [helper.make_tensor_value_info("out", TensorProto.DOUBLE, ["batch", width])], inits)
        return helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)]).SerializeToString()

    folder = tmp_path / "nan"
    folder.mkdir()
    files, digests = {}, {}
    for key, width in (("compensator", 6), ("monitor", 3)):
        data = graph(key, width)
        (folder / f"{key}.onnx").write_bytes(data)
        files[key], digests[key] = f"{key}.onnx", hashlib.sha256(data).hexdigest()
    manifest = {"format": "torchcal-compensator/1", "robot": "nan-bot", "n_joints": 6, "joint_names": [f"j{i}" for i in range(1, 7)],
                "files": files, "sha256": digests, "stages": {"stiffness": True},
                "wrench": {"frame": "tool"}}
    write_manifest(folder, manifest)
    return folder


def test_runner_refuses_non_finite_output_and_names_the_rows(tmp_path):
    """A graph output with NaN is refused with the rows named, never handed to the controller."""
    folder = _nan_folder(tmp_path)
    rt = CompensatorRuntime(folder)
    q = np.zeros((5, 6))
    sign = np.ones((5, 6))
    sign[[1, 3]] = -1.0
    with pytest.raises(CompensatorError, match=r"row\(s\) \[1, 3\]"):
        rt.correct(q, sign)
    np.testing.assert_allclose(rt.correct(q, np.ones(6)), np.zeros((5, 6)))  # finite output passes through


def test_correct_one_from_several_threads_returns_each_callers_command(exported, model_dir):
    import threading

    rt = CompensatorRuntime(exported[0])
    q = load_model(model_dir).robot.sample_joints(200, torch.Generator().manual_seed(12)).numpy()
    serial = np.stack([rt.correct_one(row)[0] for row in q])
    wrong: list[int] = []

    def caller(seed: int) -> None:
        rng = np.random.default_rng(seed)
        wrong.extend(int(i) for i in rng.integers(0, len(q), 1500) if not np.array_equal(rt.correct_one(q[i])[0], serial[i]))

    threads = [threading.Thread(target=caller, args=(seed,)) for seed in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert wrong == []  # the bound buffers are shared: without the lock one caller reads another's command


def _edit_manifest(folder: Path, edit) -> None:
    import json

    manifest = json.loads((folder / "manifest.json").read_text())
    edited = edit(manifest)
    write_manifest(folder, manifest if edited is None else edited)


def test_a_changed_manifest_or_a_missing_checksum_file_is_refused(folder):
    path = folder / "manifest.json"
    path.write_text(path.read_text().replace('"robot": "', '"robot": "x', 1))  # a robot renamed by hand
    with pytest.raises(CompensatorError, match="manifest was changed after export"):
        CompensatorRuntime(folder)
    (folder / "checksums.json").write_text('{"format": "torchcal-checksums/1", "files": ["manifest.json"]}')
    with pytest.raises(CompensatorError, match=r"recording manifest\.json"):
        CompensatorRuntime(folder)
    (folder / "checksums.json").unlink()
    with pytest.raises(CompensatorError, match=r"checksums\.json: missing"):
        CompensatorRuntime(folder)


@pytest.mark.parametrize("edit, message", [
    (lambda m: [], "not a JSON object"),
    (lambda m: m.pop("robot") and None, "robot must be a name"),
    (lambda m: m.update(n_joints="6"), "n_joints must be a whole number"),
    (lambda m: m.update(joint_names=["a", "b"]), "joint_names must list"),
    (lambda m: m["joint_limits_rad"].__setitem__(2, [1.0, -1.0]), r"joint_limits_rad\[2\]"),
    (lambda m: m["files"].update(compensator="../elsewhere/compensator.onnx"), "must name a file inside the folder"),
    (lambda m: m.update(outputs=["q_corrected"]), "outputs must be an object"),
])
def test_a_malformed_manifest_is_a_compensator_error(folder, edit, message):
    _edit_manifest(folder, edit)
    with pytest.raises(CompensatorError, match=message):
        CompensatorRuntime(folder)


@pytest.mark.parametrize("other, message", [("monitor", "not the manifest's compensator outputs"),
                                            ("compensator_f32", "not the manifest's tensor\\(double\\)")])
def test_a_manifest_pointing_at_another_graph_is_refused(folder, other, message):
    def point(manifest):
        manifest["files"]["compensator"] = manifest["files"][other]
        manifest["sha256"]["compensator"] = manifest["sha256"][other]

    _edit_manifest(folder, point)
    with pytest.raises(CompensatorError, match=message):
        CompensatorRuntime(folder)


def test_joints_outside_the_limits_or_not_numbers_are_refused(exported):
    rt = CompensatorRuntime(exported[0])
    low, high = np.array(rt.manifest["joint_limits_rad"]).T
    inside = (low + high) / 2
    at_limit = inside.copy()
    at_limit[1] = high[1] + 1e-9  # rounding at a limit passes
    assert rt.correct(at_limit).shape == (6,)
    beyond = np.stack([inside, inside])
    beyond[1, 0] = 1e6  # degrees, or millidegrees, given as radians
    for call in (rt.correct, rt.predict_error, lambda q: rt.correct_one(q[1])):
        with pytest.raises(CompensatorError, match="outside its limits"):
            call(beyond)
    for bad in (["a"] * 6, np.ones(6, dtype=bool), inside + 0.5j, [[0.0] * 6, [0.0] * 5]):
        with pytest.raises(CompensatorError, match=r"real numbers|not an array of numbers"):
            rt.correct(bad)
    with pytest.raises(CompensatorError, match="real numbers"):
        rt.correct_one(np.array(["x"] * 6, dtype=object))


@pytest.mark.parametrize("threads", [0, -1, 1.5, True])
def test_a_thread_count_below_one_is_refused(exported, threads):
    with pytest.raises(CompensatorError, match="threads must be"):
        CompensatorRuntime(exported[0], threads=threads)
