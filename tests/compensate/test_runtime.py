"""The controller-side runtime: integrity and input checks, and no torch."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchcal.compensate.export import build_graphs
from torchcal.compensate.runtime import CompensatorError, CompensatorRuntime
from torchcal.errors import TorchcalError
from torchcal.model_store import load_model

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture()
def folder(exported, tmp_path):
    copy = tmp_path / "exported"
    shutil.copytree(exported[0], copy)
    return copy


def test_runtime_matches_torch(exported, model_dir):
    rt = CompensatorRuntime(exported[0])
    stored = load_model(model_dir)
    graphs = build_graphs(stored)
    q = stored.robot.sample_joints(50, torch.Generator().manual_seed(31))
    with torch.no_grad():
        ref = graphs["compensator"](q).numpy()
    np.testing.assert_allclose(rt.correct(q.numpy()), ref, atol=1e-12)
    np.testing.assert_allclose(rt.correct(q[0].numpy()), ref[0], atol=1e-12)  # single pose
    assert rt.predict_error(q.numpy()).shape == (50, 3)
    rt32 = CompensatorRuntime(exported[0], precision="float32", threads=1)
    assert rt32.correct(q.numpy()).dtype == np.float32


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
    manifest["n_joints"] = 7
    (folder / "manifest.json").write_text(json.dumps(manifest))
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


def test_non_finite_output_is_refused_not_returned(exported):
    """At exactly singular wrist poses the float32 solve can lose its pivot: the runner must refuse."""
    import onnxruntime as ort

    folder, manifest = exported
    gen = torch.Generator().manual_seed(5)
    q = (torch.rand(2000, 6, generator=gen, dtype=torch.float64) - 0.5) * 2.0
    q[:, 4] = (torch.rand(2000, generator=gen, dtype=torch.float64) - 0.5) * 2e-3  # |q5| < 1e-3 rad
    session = ort.InferenceSession(str(folder / manifest["files"]["compensator_f32"]), providers=["CPUExecutionProvider"])
    raw = session.run(None, {session.get_inputs()[0].name: q.float().numpy()})[0]
    bad = np.flatnonzero(~np.isfinite(raw).all(axis=1))
    if bad.size == 0:
        pytest.skip("this onnxruntime build kept every float32 pivot; nothing to refuse")
    rt32 = CompensatorRuntime(folder, precision="float32")
    with pytest.raises(CompensatorError, match=rf"row\(s\) \[{bad[0]}"):
        rt32.correct(q.numpy())
    # the float64 graph is finite on the same poses
    assert np.isfinite(CompensatorRuntime(folder).correct(q.numpy())).all()
