"""ONNX export of a model folder: compensator and monitor graphs, manifest, README.

Files written to ``out_dir`` (each atomically, single-file ONNX without external data):

* ``compensator.onnx`` / ``compensator_f32.onnx``: ``q_nominal (batch, N)`` rad ->
  ``q_corrected (batch, N)`` rad and ``residual (batch, 2)``: the model's remaining TCP position
  error (m) and orientation deviation (rad) at the corrected command; float64 / float32;
* ``monitor.onnx`` / ``monitor_f32.onnx``: ``q (batch, N)`` rad -> ``tcp_error_m (batch, 3)``,
  the predicted TCP position error in the robot ``base`` frame, m;
* with a stiffness stage in the model folder, both graphs take a second input ``wrench``
  ``(batch, 6)``: ``[fx, fy, fz]`` N applied at the TCP and ``[tx, ty, tz]`` N m about the TCP,
  along the tool axes (``wrench_frame="base"``: along the robot base axes), the expected load
  of the command (:data:`WRENCH_INPUT`);
* ``manifest.json``: what the files are, where they come from, their SHA-256 and their accuracy;
* ``README.md``: for the controller integrator;
* ``checksums.json``: SHA-256 of each of these files.

The folder is built in a hidden sibling and swapped into place when complete
(:func:`torchcal.core.folder.staged_folder`): an interrupted export leaves the earlier export, whole.
"""

from __future__ import annotations

import json
import math
import platform
from pathlib import Path

import torch

import torchcal
from torchcal.compensate.compensator import (
    DEFAULT_TASK,
    RESIDUAL_OUTPUT,
    TASKS,
    CompensatorGraph,
    CompensatorWithResidual,
)
from torchcal.compensate.export_checks import (
    convergence_report,
    float32_budget,
    regular_poses,
)
from torchcal.compensate.export_readme import readme_text
from torchcal.compensate.graphs import (
    GRAPHS,
    OPSET,
    WRENCH_INPUT,
    build_graphs,
    check_tool_length,
    compensator_of,
    float32_compensator_bytes,
    has_wrench_input,
    onnx_bytes,
    uses_contrib_inverse,
)
from torchcal.compensate.onnx_checks import ort_feeds, ort_session
from torchcal.compensate.production_tcp import (
    MAX_JOINT_CORRECTION_DEG,
    MAX_TOOL_ROTATION_DEG,
    check_corrections,
    correction_extent,
    production_view,
    tcp_entry,
    tcp_transform,
)
from torchcal.compensate.true_robot_check import compensation_on_true_robot
from torchcal.core.errors import TorchcalError
from torchcal.core.folder import check_output_folder, staged_folder
from torchcal.core.hashing import sha256_bytes
from torchcal.core.io import atomic_write_bytes, atomic_write_json, atomic_write_text
from torchcal.core.metrics import position_metrics
from torchcal.identify.joint_errors import METADATA_KEYS
from torchcal.stages.base import ModelStage
from torchcal.stages.prediction_uncertainty import load_uncertainty, stored_prediction
from torchcal.stages.store import load_model

MANIFEST_FORMAT = "torchcal-compensator/1"


def _versions() -> dict:
    import onnx
    import onnxruntime

    return {
        "torchcal": torchcal.__version__,
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "onnxruntime": onnxruntime.__version__,
        "python": platform.python_version(),
    }


def _held_out_metrics(model_dir: Path, meta: dict) -> dict | None:
    """Held-out metrics stored with the model, if any (``metrics.json`` or calibration.json)."""
    for key in ("held_out", "test_metrics", "metrics"):
        if isinstance(meta.get(key), dict):
            return meta[key]
    path = model_dir / "metrics.json"
    if path.is_file():
        return json.loads(path.read_text())
    return _cross_validated_metrics(model_dir)


def _cross_validated_metrics(model_dir: Path) -> dict | None:
    """Without held-out figures in the model folder: the fit's own grouped cross-validation of the
    chosen model (out-of-fold poses, the protocol stated), from ``model_selection.json``."""
    path = model_dir / "model_selection.json"
    if not path.is_file():
        return None
    selection = json.loads(path.read_text())
    chosen = next((c for c in selection.get("candidates", []) if c.get("name") == selection.get("chosen")), None)
    if chosen is None:
        return None
    return {"position_rms_mm": chosen["cv_rms_mm"], "model": selection["chosen"],
            "protocol": f"cross-validated in the fit: {selection.get('protocol', '')}",
            "note": "out-of-fold poses of the training file; `torchcal evaluate` on new poses measures the model itself"}


def _expected_accuracy(stored) -> dict | None:
    """The model's predicted 95th percentile of the 3-D error over its training poses' workspace."""
    calibration = load_uncertainty(stored.folder)
    if calibration is None or stored.training_q is None:
        return None
    prediction = stored_prediction(stored, stored.training_q)
    assert prediction is not None  # a calibration was found above
    return {"p95_mm": prediction.set_p95_mm, "level": 0.95, "method": calibration.method,
            "protocol": f"calibrated on the out-of-fold errors of {calibration.protocol}",
            "where": "poses like the training poses (the same workspace and configurations); the accuracy the "
                     "compensated robot reaches adds the compensator's own error (float32_error_budget)"}


#: The most Newton steps an export unrolls (each adds its nodes to the graph; 6 solve 99.5 % of poses).
MAX_ITERATIONS = 50


def export_model(
    model_dir: str | Path,
    out_dir: str | Path,
    *,
    wrench_frame: str = "tool",
    iterations: int | None = None,
    portable: bool = False,
    task: str = DEFAULT_TASK,
    tcp_mm: list[float] | None = None,
    tcp_rpy_deg: list[float] | None = None,
    allow_large_corrections: bool = False,
    tool_length_mm: float = 0.0,
) -> dict:
    """Export the compensator of a model folder; returns the manifest (also written to disk).

    ``tcp_mm`` / ``tcp_rpy_deg``: the production TCP in the flange frame (mm, fixed-axis XYZ deg;
    default: the flange), the point the compensator serves (:mod:`torchcal.compensate.production_tcp`),
    stated in the manifest's ``tcp``; the calibration's measured point (the reflector) is not its target.
    ``allow_large_corrections``: export even when a joint correction or the tool orientation
    deviation exceeds the stated limits (otherwise refused). ``tool_length_mm``: keep the nominal
    command wherever the corrected one would leave a point that far beyond the TCP further off
    (position error plus length times the tool's turn; 0: the TCP's position alone is judged).

    ``wrench_frame`` (``tool`` | ``base``) sets the axes of the ``wrench`` input of a model
    folder with a stiffness stage; it is recorded in the manifest. ``task``: ``position``
    (default: position exactly, orientation as far as the position leaves room) or ``pose``
    (full 6-D). ``iterations``: Newton steps of the compensator (``None``: the task's default;
    the manifest's ``convergence`` shows what they reach). ``portable``: standard ONNX operators
    only.
    """
    if iterations is not None and not 1 <= iterations <= MAX_ITERATIONS:
        raise TorchcalError(f"--iterations must be in [1, {MAX_ITERATIONS}] (Newton steps unrolled into the graph), "
                            f"got {iterations}")
    if task not in TASKS:
        raise TorchcalError(f"task must be one of {list(TASKS)}, got {task!r}")
    check_tool_length(tool_length_mm)
    model_dir, out_dir = Path(model_dir), Path(out_dir)
    if out_dir.resolve() == model_dir.resolve():
        raise TorchcalError(f"{out_dir}: the export folder must lie outside the model folder {model_dir}")
    check_output_folder(out_dir, purpose="export")
    stored = load_model(model_dir)
    T_tcp = tcp_transform(tcp_mm, tcp_rpy_deg)
    tcp = tcp_entry(T_tcp, tcp_mm, tcp_rpy_deg, stored)
    stored = production_view(stored, T_tcp)
    with staged_folder(out_dir, purpose="export") as staging:
        return _export_into(staging, model_dir, stored, wrench_frame=wrench_frame, iterations=iterations,
                            portable=portable, task=task, tcp=tcp, allow_large_corrections=allow_large_corrections,
                            tool_length=tool_length_mm * 1e-3)


def turned_tool_warning(manifest: dict) -> str | None:
    """A warning where the position-first commands turn the tool by degrees beyond the nominal command's
    (the convergence report's uniform poses), unless ``--tool-length-mm`` already guards against it."""
    strata = manifest["convergence"]["strata"]
    uniform, wrist = strata["uniform"], strata["wrist_singular"]
    shares = [s.get("share_tool_turn_added_above_1_deg") or 0.0 for s in (uniform, wrist)]
    if manifest["solver"].get("tool_length_m", 0.0) > 0 or not any(shares):
        return None
    largest = max(s["tool_turn_added_rad"]["max"] for s in (uniform, wrist) if "tool_turn_added_rad" in s)
    return (f"to hold the TCP position the commands turn the tool more than 1 deg beyond the nominal command on "
            f"{100 * shares[0]:.1f} % of random poses and {100 * shares[1]:.1f} % near the wrist singularity (up to "
            f"{math.degrees(largest):.2g} deg, near the elbow, shoulder or wrist singularity); "
            "a tool beyond the exported TCP then misses by its length times that turn: export for the tool's point "
            "(--tcp-mm) or give --tool-length-mm (docs/export.md)")


def _export_into(out_dir: Path, model_dir: Path, stored, *, wrench_frame: str, iterations: int | None,
                 portable: bool, task: str, tcp: dict | None = None, allow_large_corrections: bool = True,
                 tool_length: float = 0.0) -> dict:
    """Write the export files of ``stored`` into ``out_dir`` (a staging folder); returns the manifest."""
    graphs = build_graphs(stored, wrench_frame=wrench_frame, iterations=iterations, portable=portable, task=task,
                          tool_length=tool_length)
    extent = {}
    if not has_wrench_input(graphs):
        if stored.training_q is not None and len(regular_poses(stored.robot, stored.training_q)):
            extent["training poses"] = correction_extent(compensator_of(graphs), regular_poses(stored.robot, stored.training_q),
                                                         stored)
        extent["joint range"] = correction_extent(
            compensator_of(graphs), regular_poses(stored.robot, stored.robot.sample_joints(2000, torch.Generator().manual_seed(2))))
    exceeded = check_corrections(extent, allow_large_corrections)
    loaded = has_wrench_input(graphs)
    robot = stored.robot
    files, digests = {}, {}
    written: dict[str, bytes] = {}
    for key, (name, dtype, input_name, output_name) in GRAPHS.items():
        is_compensator = key.startswith("compensator")
        if key == "compensator_f32":  # the float64 graph's parts behind float32 inputs and outputs
            data = float32_compensator_bytes(written["compensator"])
        else:
            module = CompensatorWithResidual(compensator_of(graphs, key)) if is_compensator else graphs[key]
            data = onnx_bytes(module, robot.dof, dtype, input_name, output_name, wrench_input=WRENCH_INPUT if loaded else None,
                              extra_outputs=(RESIDUAL_OUTPUT,) if is_compensator else ())
        written[key] = data
        atomic_write_bytes(out_dir / name, data)
        files[key] = name
        digests[key] = sha256_bytes(data)
    meta = stored.metadata
    compensator = compensator_of(graphs)
    stages = stored.stages()
    manifest = {
        "format": MANIFEST_FORMAT,
        "robot": robot.name,
        "n_joints": robot.dof,
        "joint_names": list(robot.joint_names),
        # JSON has no infinity: a continuous joint's limits are null (it is never clipped)
        "joint_limits_rad": [None if cont else lim
                             for lim, cont in zip(robot.joint_limits.tolist(), robot.continuous.tolist())],
        "continuous_joints": [name for name, cont in zip(robot.joint_names, robot.continuous.tolist()) if cont],
        "units": {
            "compensator": {"input": "q_nominal, rad", "output": "q_corrected, rad",
                            RESIDUAL_OUTPUT: "(batch, 2): remaining TCP position error of the model at q_corrected, m, "
                                             "and orientation deviation of the tool from the nominal target, rad "
                                             "(through the kinematics once more after the last step)"},
            "monitor": {"input": "q, rad", "output": "tcp_error_m: predicted TCP position error, m, robot base frame"},
        },
        "frames": "robot base frame (calibrated); the instrument frame of the calibration is not applied",
        "sign_convention": "dT = T_real(q) - T_nominal(q) (monitor output); T_c = T_t - dT; q_corrected = IK_nominal(T_c)",
        "stages": _stages(stages),
        "inputs": {"compensator": "q_nominal", "monitor": "q"},
        "outputs": {"compensator": ["q_corrected", RESIDUAL_OUTPUT], "monitor": ["tcp_error_m"]},
        "dtypes": {key: str(dtype).replace("torch.", "") for key, (_, dtype, _, _) in GRAPHS.items()},
        "opset": OPSET,
        "iterations": compensator.iterations,
        "solver": _solver_description(compensator, portable),
        "runtime": "onnxruntime (the compensators use the contrib operator com.microsoft.Inverse, domain version 1)"
                   if uses_contrib_inverse(compensator) else f"any ONNX runtime (standard operators, opset {OPSET})",
        "training_data": {"sha256": meta.get("data", {}).get("sha256"), "n_poses": meta.get("data", {}).get("n_poses"),
                          "of": ("the new poses of the update that wrote the model" if meta.get("method") == "update"
                                 else "the poses of the fit that wrote the model"),
                          "n_poses_all_fits": None if stored.training_q is None else len(stored.training_q)},
        "calibration": {"method": meta.get("method"), "residual_sigma_mm": meta.get("residual_sigma_mm")},
        "held_out_metrics": _held_out_metrics(model_dir, meta),
        "expected_accuracy_95": _expected_accuracy(stored),
        "versions": _versions(),
        "tcp": tcp,
        "corrections": {"limits": _correction_limits(), "extent": extent, "exceeded_but_allowed": exceeded},
        "files": files,
        "sha256": digests,
    }
    for stage in stages:  # each stage's own entry (the stiffness: its springs and data)
        section = stage.manifest_section()
        if section is not None:
            manifest[stage.name] = section
    if loaded:
        _describe_wrench_input(manifest, wrench_frame)
    manifest["float32_error_budget"] = float32_budget(graphs, out_dir, stored)
    manifest["convergence"] = convergence_report(graphs, stored)
    atomic_write_json(out_dir / "manifest.json", manifest)
    sections = [text for text in (stage.readme_section(manifest) for stage in stages) if text]
    atomic_write_text(out_dir / "README.md", readme_text(manifest, sections))
    return manifest


#: What the compensator orients the tool by (``solver.orientation_source``), in the manifest's words.
ORIENTATION_SOURCE_NOTES = {
    "geometry": ("the tool's orientation target is met by the calibrated MDH table alone (to second order in the "
                 "joint-space terms): the calibration measured positions only, and joint-space terms fitted to positions "
                 "correct the position without claiming the tool's turn (measured on the IRB 120's three SMRs: such "
                 "terms turn the tool 5x further from the truth than the nominal robot; docs/prior.md)"),
    "model": "the tool's orientation target is met by the whole calibrated chain, joint-space terms included",
}


def _correction_limits() -> dict:
    return {"median_joint_correction_deg": MAX_JOINT_CORRECTION_DEG, "median_tool_rotation_deg": MAX_TOOL_ROTATION_DEG,
            "judged": ("the median over the training poses (over the joint range for a model that keeps none; the "
                       "largest and the other set are reported, not judged: near, not at, a singularity any orientation "
                       "step is large); beyond it export refuses unless --allow-large-corrections is given"),
            "sampling": ("the model's training poses and 2000 poses uniform within the joint limits (seed 2), both less "
                         "those in the convergence report's singular strata")}


def _solver_description(compensator: CompensatorGraph, portable: bool) -> dict:
    """The manifest's ``solver`` entry: task, steps, damping and linear solve of the compensator."""
    common = {
        "damping": "lambda^2 = gain * |e|^2 + floor^2",
        "damping_gain": float(compensator.damping_gain),
        "damping_floor": math.sqrt(float(compensator.damping_floor_sq)),
        "max_step_rad": float(compensator.max_step),
        "joint_limits": "every iterate is clipped to joint_limits_rad (null: a continuous joint, not clipped)",
        "kept_nominal": (
            f"the nominal command is sent wherever the corrected one would leave a point {compensator.tool_length * 1e3:g} mm "
            "beyond the TCP further off (bound: position error + that length * orientation deviation, by the model)"
            if compensator.tool_length > 0 else
            "the nominal command is sent wherever the corrected one would leave the TCP position further off (by the model)"),
        "tool_length_m": compensator.tool_length,
        "orientation_source": compensator.orientation_source,
        "orientation_source_note": (ORIENTATION_SOURCE_NOTES[compensator.orientation_source]
                                    if compensator.models.joint_errors is not None else
                                    "the tool's orientation target is met by the calibrated chain (the model has no "
                                    "joint-space terms, so both sources are the same)"),
    }
    if compensator.task == "pose":
        return {
            "task": "pose",
            "method": "damped least squares on the 6-D pose from q_nominal, each pose until converged (at most `iterations` steps)",
            **common,
            "linear_solve": (
                "6x6, float64 in every variant: unrolled Gauss-Jordan (standard ONNX operators)" if portable else
                "6x6, float64 in every variant: com.microsoft.Inverse (onnxruntime contrib operator, LU with partial pivoting)"
            ),
        }
    return {
        "task": "position",
        "method": ("task-priority damped least squares from q_nominal: the TCP position first, the orientation in the "
                   f"position task's null space; each pose until converged, at most {compensator.orientation_steps} such steps "
                   f"then at most {compensator.iterations - compensator.orientation_steps} position-only ones"),
        **common,
        "orientation_damping_floor": math.sqrt(float(compensator.orientation_damping_sq)),
        "max_orientation_step_rad": float(compensator.max_orientation_step),
        "linear_solve": (
            "two 3x3 systems per step, float64 in every variant: closed-form adjugate (standard ONNX operators)" if portable else
            "two 3x3 systems per step, float64 in every variant: com.microsoft.Inverse (onnxruntime contrib operator)"
        ),
    }


def _stages(stages: list[ModelStage]) -> dict[str, bool]:
    """``stages`` of the manifest: every stage kind, present or not, from the model's own stage list."""
    entries = {"geometry": False, "residual": False, "stiffness": False, **dict.fromkeys(METADATA_KEYS.values(), False)}
    for stage in stages:
        entries.update(stage.describe())
    return entries


def _describe_wrench_input(manifest: dict, wrench_frame: str) -> None:
    """Manifest entries of the ``wrench`` input of graphs with a stiffness stage (in place)."""
    axes = "the tool (TCP) axes at the commanded pose, as an F/T sensor at the TCP reports them" if wrench_frame == "tool" else "the robot base axes"
    for key in ("compensator", "monitor"):
        manifest["units"][key]["input"] += f"; {WRENCH_INPUT}, N and N m, {wrench_frame} frame"
    manifest["units"]["monitor"]["output"] += " (loaded TCP under the wrench input, minus the nominal unloaded TCP)"
    manifest["extra_inputs"] = {"compensator": [WRENCH_INPUT], "monitor": [WRENCH_INPUT]}
    manifest["wrench"] = {
        "name": WRENCH_INPUT,
        "shape": "(batch, 6)",
        "components": ["fx", "fy", "fz", "tx", "ty", "tz"],
        "units": ["N", "N", "N", "N m", "N m", "N m"],
        "frame": wrench_frame,
        "axes": axes,
        "point": "force applied at the TCP, moment about the TCP",
        "payload": (
            "a payload of mass m (kg) with centre of mass c (m, tool frame) hanging at the tool: "
            "f = m g and moment c x f, with g = R_base_tool^T [0, 0, -9.81] in the tool frame "
            "(the base z axis pointing up)" if wrench_frame == "tool" else
            "a payload of mass m (kg) with centre of mass c (m, from the TCP, base axes): f = m [0, 0, -9.81], moment c x f"
        ),
        "zero": "a zero wrench gives the unloaded compensation (geometry and residual only)",
    }
    manifest["sign_convention"] += "; with stiffness, T_real is the loaded TCP under the wrench input"


def export_and_check(model_dir: str | Path, out_dir: str | Path, test, true_tcp_positions=None,
                     tcp_mm: list[float] | None = None, tcp_rpy_deg: list[float] | None = None) -> dict:
    """Export (production TCP ``tcp_mm`` / ``tcp_rpy_deg``, default the flange), then run the exported
    graphs with onnxruntime on the test poses.

    Returns parity numbers (ORT against the torch graphs of the same TCP, mm and rad) and the
    held-out position error of the model's monitor at the measured point (instrument frame, mm,
    no re-registration: the test file measures that point, not the production TCP). With
    ``true_tcp_positions`` (``(q, T_flange_tcp) -> (B, 3)`` true position of a TCP in the instrument
    frame, m: a twin's truth, :meth:`~torchcal.sim.twin.Twin.true_tcp_positions`), also
    ``compensation_on_true_robot``: the commands of torch and of both exported files at the test
    poses, sent to that robot, scored at the exported TCP
    (:func:`~torchcal.compensate.true_robot_check.compensation_on_true_robot`).
    """
    out_dir = Path(out_dir)
    manifest = export_model(model_dir, out_dir, tcp_mm=tcp_mm, tcp_rpy_deg=tcp_rpy_deg)
    measured = load_model(model_dir)
    T_tcp = tcp_transform(tcp_mm, tcp_rpy_deg)
    stored = production_view(measured, T_tcp)  # what the files serve
    graphs = build_graphs(stored)
    q = test.q.to(torch.float64)
    wrench = None
    if has_wrench_input(graphs):  # the file's wrench (tool frame) where it has one, else unloaded
        wrench = getattr(test, "wrench", None)
        wrench = torch.zeros(len(q), 6, dtype=torch.float64) if wrench is None else wrench.to(torch.float64)
    args = (q,) if wrench is None else (q, wrench)
    w = None if wrench is None else wrench.numpy()
    with torch.no_grad():
        ref_cmd = graphs["compensator"](*args)
        ref_mon = graphs["monitor"](*args)
    session = ort_session(out_dir / manifest["files"]["compensator"])
    ort_cmd = torch.from_numpy(session.run(None, ort_feeds(session, q.numpy(), w))[0])
    session = ort_session(out_dir / manifest["files"]["monitor"])
    ort_mon = torch.from_numpy(session.run(None, ort_feeds(session, q.numpy(), w))[0])
    model = stored.model
    tcp = lambda qq: (model.base_flange_pose(qq, stored.x) @ model.flange_from_tool(stored.x))[..., :3, 3]  # noqa: E731
    with torch.no_grad():
        measured_monitor = build_graphs(measured)["monitor"](*args)
    predicted_base = measured.robot.tcp_position(q) + measured_monitor
    T_ref = measured.model.instrument_from_base(measured.x)
    held_out = position_metrics(test.position - (predicted_base @ T_ref[:3, :3].T + T_ref[:3, 3]))
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
    if true_tcp_positions is not None:
        result["compensation_on_true_robot"] = compensation_on_true_robot(
            stored, graphs, out_dir, manifest, q, lambda qq: true_tcp_positions(qq, T_tcp), wrench)
    result["summary"] = (
        f"export: {out_dir} (compensator ORT vs torch {result['compensator_tcp_max_mm']:.1e} mm, "
        f"float32 budget {manifest['float32_error_budget']['compensator_tcp_mm']['max']:.1e} mm)")
    result["turned_tool_warning"] = turned_tool_warning(manifest)
    return result
