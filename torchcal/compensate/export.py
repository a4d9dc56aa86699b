"""ONNX export of a model folder: compensator and monitor graphs, manifest, README.

Files written to ``out_dir`` (each atomically, single-file ONNX without external data):

* ``compensator.onnx`` / ``compensator_f32.onnx``: ``q_nominal (batch, N)`` rad ->
  ``q_corrected (batch, N)`` rad, float64 / float32;
* ``monitor.onnx`` / ``monitor_f32.onnx``: ``q (batch, N)`` rad -> ``tcp_error_m (batch, 3)``,
  the predicted TCP position error in the robot ``base`` frame, m;
* ``manifest.json``: what the files are, where they come from, their SHA-256 and their accuracy;
* ``README.md``: for the controller integrator.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import platform
import warnings
from pathlib import Path

import torch

from torchcal.compensate.compensator import CompensatorGraph, MonitorGraph
from torchcal.io import atomic_write_bytes, atomic_write_json, atomic_write_text

OPSET = 17
MANIFEST_FORMAT = "torchcal-compensator/1"
GRAPHS = {
    "compensator": ("compensator.onnx", torch.float64, "q_nominal", "q_corrected"),
    "compensator_f32": ("compensator_f32.onnx", torch.float32, "q_nominal", "q_corrected"),
    "monitor": ("monitor.onnx", torch.float64, "q", "tcp_error_m"),
    "monitor_f32": ("monitor_f32.onnx", torch.float32, "q", "tcp_error_m"),
}
BUDGET_POSES = 10_000


def onnx_bytes(module: torch.nn.Module, n_joints: int, dtype: torch.dtype, input_name: str, output_name: str) -> bytes:
    """Serialize ``module`` to ONNX (opset :data:`OPSET`, dynamic batch axis) in memory.

    The TorchScript exporter (``dynamo=False``) is used: the dynamo exporter needs onnxscript,
    which a calibration PC may not have, and the graphs hold no data-dependent control flow.
    """
    buffer = io.BytesIO()
    example = torch.zeros(2, n_joints, dtype=dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's deprecation notices, not about this graph
        torch.onnx.export(
            module.eval(),
            (example,),
            buffer,
            dynamo=False,
            opset_version=OPSET,
            input_names=[input_name],
            output_names=[output_name],
            dynamic_axes={input_name: {0: "batch"}, output_name: {0: "batch"}},
            do_constant_folding=True,
        )
    return buffer.getvalue()


def build_graphs(stored, residual: torch.nn.Module | None = None, *, use_stored_residual: bool = True) -> dict[str, torch.nn.Module]:
    """The four torch modules of :data:`GRAPHS` for a :class:`StoredModel`."""
    if residual is None and use_stored_residual and stored.residual is not None:
        residual = stored.residual.to_torch_module()
    graphs = {}
    for key, (_, dtype, _, _) in GRAPHS.items():
        cls = CompensatorGraph if key.startswith("compensator") else MonitorGraph
        graphs[key] = cls(stored.model, stored.x, residual, dtype=dtype).eval()
    return graphs


def sha256_file(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _versions() -> dict:
    import onnx
    import onnxruntime

    import torchcal

    return {
        "torchcal": torchcal.__version__,
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "onnxruntime": onnxruntime.__version__,
        "python": platform.python_version(),
    }


def _session(path: Path):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def float32_budget(graphs: dict[str, torch.nn.Module], out_dir: Path, stored, n_poses: int = BUDGET_POSES, seed: int = 0) -> dict:
    """Float32 error of the exported files against the float64 torch graphs, measured in mm.

    Poses: ``n_poses`` uniform within the joint limits. Compensator: 3-D distance between the
    calibrated TCP at the float32 ORT command and at the float64 torch command. Monitor: 3-D
    distance of the predicted errors.
    """
    q = stored.robot.sample_joints(n_poses, torch.Generator().manual_seed(seed))
    with torch.no_grad():
        qc64 = graphs["compensator"](q)
        mon64 = graphs["monitor"](q)
    qc32 = torch.from_numpy(_session(out_dir / GRAPHS["compensator_f32"][0]).run(None, {"q_nominal": q.float().numpy()})[0]).double()
    mon32 = torch.from_numpy(_session(out_dir / GRAPHS["monitor_f32"][0]).run(None, {"q": q.float().numpy()})[0]).double()
    model = stored.model
    tcp = lambda qq: model.base_flange_pose(qq, stored.x) @ model.flange_from_tool(stored.x)  # noqa: E731
    d_cmd = (tcp(qc32)[..., :3, 3] - tcp(qc64)[..., :3, 3]).norm(dim=-1) * 1e3
    d_mon = (mon32 - mon64).norm(dim=-1) * 1e3
    return {
        "n_poses": n_poses,
        "sampling": "uniform within joint limits, seed %d" % seed,
        "compensator_tcp_mm": {"max": float(d_cmd.max()), "p99": float(d_cmd.quantile(0.99)), "median": float(d_cmd.median())},
        "compensator_joint_rad_max": float((qc32 - qc64).abs().max()),
        "monitor_mm": {"max": float(d_mon.max()), "p99": float(d_mon.quantile(0.99)), "median": float(d_mon.median())},
    }


def _held_out_metrics(model_dir: Path, meta: dict) -> dict | None:
    """Held-out metrics stored with the model, if any (``metrics.json`` or calibration.json)."""
    for key in ("held_out", "test_metrics", "metrics"):
        if isinstance(meta.get(key), dict):
            return meta[key]
    path = model_dir / "metrics.json"
    if path.is_file():
        return json.loads(path.read_text())
    return None


def export_model(model_dir: str | Path, out_dir: str | Path) -> dict:
    """Export the compensator of a model folder; returns the manifest (also written to disk)."""
    from torchcal.model_store import load_model

    model_dir, out_dir = Path(model_dir), Path(out_dir)
    stored = load_model(model_dir)
    if stored.metadata.get("gravity_compliance"):
        from torchcal.errors import TorchcalError

        raise TorchcalError(f"{model_dir}: the compensator graph has no gravity-compliance term yet; "
                            "fit with gravity_compliance=none to export")
    graphs = build_graphs(stored)
    robot = stored.robot
    files, digests = {}, {}
    for key, (name, dtype, input_name, output_name) in GRAPHS.items():
        data = onnx_bytes(graphs[key], robot.dof, dtype, input_name, output_name)
        atomic_write_bytes(out_dir / name, data)
        files[key] = name
        digests[key] = hashlib.sha256(data).hexdigest()
    meta = stored.metadata
    compensator = graphs["compensator"]
    manifest = {
        "format": MANIFEST_FORMAT,
        "robot": robot.name,
        "n_joints": robot.dof,
        "joint_names": list(robot.joint_names),
        "joint_limits_rad": robot.joint_limits.tolist(),
        "units": {
            "compensator": {"input": "q_nominal, rad", "output": "q_corrected, rad"},
            "monitor": {"input": "q, rad", "output": "tcp_error_m: predicted TCP position error, m, robot base frame"},
        },
        "frames": "robot base frame (calibrated); the instrument frame of the calibration is not applied",
        "sign_convention": "dT = T_real(q) - T_nominal(q) (monitor output); T_c = T_t - dT; q_corrected = IK_nominal(T_c)",
        "stages": {"geometry": True, "residual": stored.residual is not None, "stiffness": False},
        "inputs": {"compensator": "q_nominal", "monitor": "q"},
        "outputs": {"compensator": "q_corrected", "monitor": "tcp_error_m"},
        "dtypes": {key: str(dtype).replace("torch.", "") for key, (_, dtype, _, _) in GRAPHS.items()},
        "opset": OPSET,
        "iterations": compensator.iterations,
        "solver": {
            "method": "damped Newton (damped least squares), fixed iteration count, from q_nominal",
            "damping": "lambda^2 = gain * |e|^2 + floor^2",
            "damping_gain": float(compensator.damping_gain),
            "damping_floor": math.sqrt(float(compensator.damping_floor_sq)),
        },
        "training_data": {"sha256": meta.get("data", {}).get("sha256"), "n_poses": meta.get("data", {}).get("n_poses")},
        "calibration": {"method": meta.get("method"), "residual_sigma_mm": meta.get("residual_sigma_mm")},
        "held_out_metrics": _held_out_metrics(model_dir, meta),
        "versions": _versions(),
        "files": files,
        "sha256": digests,
    }
    manifest["float32_error_budget"] = float32_budget(graphs, out_dir, stored)
    atomic_write_json(out_dir / "manifest.json", manifest)
    atomic_write_text(out_dir / "README.md", readme_text(manifest))
    return manifest


def readme_text(manifest: dict) -> str:
    """The integrator's README of an exported folder."""
    budget = manifest["float32_error_budget"]
    joints = ", ".join(manifest["joint_names"])
    residual = "yes" if manifest["stages"]["residual"] else "no"
    return f"""# Compensator for {manifest['robot']}

Exported by torchcal {manifest['versions']['torchcal']} (ONNX opset {manifest['opset']}).
Stages: geometry yes, learned residual {residual}, stiffness no.

## Files

| file | input | output |
| --- | --- | --- |
| `compensator.onnx` (float64), `compensator_f32.onnx` (float32) | `q_nominal` (batch, {manifest['n_joints']}), rad | `q_corrected` (batch, {manifest['n_joints']}), rad |
| `monitor.onnx` (float64), `monitor_f32.onnx` (float32) | `q` (batch, {manifest['n_joints']}), rad | `tcp_error_m` (batch, 3), m, robot base frame |

Joint order: {joints}. Angles in **radians** in and out (convert degrees before the call).

## Use

Give the compensator the joint command the controller computed with its nominal kinematics; send
the output to the drives instead. The real robot then puts its TCP where the nominal model
believed it would be (position and orientation), as far as the calibration knows the robot.
The monitor graph predicts, for any joint vector, where the real TCP lies relative to the nominal
one (`real - nominal`, m, base frame).

The compensator runs {manifest['iterations']} damped Newton steps (fixed, no data-dependent branches).
Near singular poses the damping keeps the correction small instead of exact. Joint limits are not
enforced by the graph: the controller's limit checks stay in charge.

Check `sha256` in `manifest.json` before loading (`torchcal.compensate.runtime.CompensatorRuntime`
does; it needs only onnxruntime and numpy). Run single poses with `intra_op_num_threads=1`.

## Accuracy of float32

Measured at export on {budget['n_poses']} random poses within the joint limits, against the float64
graph: compensated TCP within {budget['compensator_tcp_mm']['max']:.2e} mm (max), monitor within
{budget['monitor_mm']['max']:.2e} mm (max). Use the float64 files where the controller allows it.
"""


def export_and_check(model_dir: str | Path, out_dir: str | Path, test, console=None) -> dict:
    """Export, then run the exported graphs with onnxruntime on the test poses.

    Returns parity numbers (ORT against the torch graphs, mm and rad) and the held-out position
    error of the exported monitor graph (instrument frame, mm, no re-registration).
    """
    from torchcal.metrics import position_metrics
    from torchcal.model_store import load_model

    out_dir = Path(out_dir)
    manifest = export_model(model_dir, out_dir)
    stored = load_model(model_dir)
    graphs = build_graphs(stored)
    q = test.q.to(torch.float64)
    with torch.no_grad():
        ref_cmd = graphs["compensator"](q)
        ref_mon = graphs["monitor"](q)
    ort_cmd = torch.from_numpy(_session(out_dir / manifest["files"]["compensator"]).run(None, {"q_nominal": q.numpy()})[0])
    ort_mon = torch.from_numpy(_session(out_dir / manifest["files"]["monitor"]).run(None, {"q": q.numpy()})[0])
    model = stored.model
    tcp = lambda qq: (model.base_flange_pose(qq, stored.x) @ model.flange_from_tool(stored.x))[..., :3, 3]  # noqa: E731
    nominal = stored.robot.tcp_position(q)
    predicted_base = nominal + ort_mon
    rot, trans = model.instrument_from_base(stored.x)[:3, :3], model.instrument_from_base(stored.x)[:3, 3]
    held_out = position_metrics(test.position - (predicted_base @ rot.T + trans))
    result = {
        "out_dir": str(out_dir),
        "n_poses": len(test),
        "compensator_joint_max_rad": float((ort_cmd - ref_cmd).abs().max()),
        "compensator_tcp_max_mm": float((tcp(ort_cmd) - tcp(ref_cmd)).norm(dim=-1).max() * 1e3),
        "monitor_max_mm": float((ort_mon - ref_mon).norm(dim=-1).max() * 1e3),
        "float32_error_budget": manifest["float32_error_budget"],
        "held_out_monitor": held_out,
        "sha256_compensator": manifest["sha256"]["compensator"],
    }
    if console is not None:
        console.log(
            f"export: {out_dir} (compensator ORT vs torch {result['compensator_tcp_max_mm']:.1e} mm, "
            f"float32 budget {manifest['float32_error_budget']['compensator_tcp_mm']['max']:.1e} mm)"
        )
    return result
