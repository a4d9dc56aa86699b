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

import io
import json
import math
import platform
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

import torchcal
from torchcal.compensate.compensator import (
    DEFAULT_TASK,
    GRAPH_CLASSES,
    RESIDUAL_OUTPUT,
    TASKS,
    CompensatorGraph,
    CompensatorWithResidual,
    graph_inputs,
    graph_parts,
)
from torchcal.compensate.linalg import CONTRIB_DOMAIN
from torchcal.compensate.onnx_checks import ort_feeds, ort_session, unsolved_distance_m
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
from torchcal.core.errors import ModelError, TorchcalError
from torchcal.core.folder import check_output_folder, staged_folder
from torchcal.core.hashing import sha256_bytes
from torchcal.core.io import atomic_write_bytes, atomic_write_json, atomic_write_text
from torchcal.core.metrics import position_metrics
from torchcal.identify.joint_errors import METADATA_KEYS
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.stages.base import ModelStage
from torchcal.stages.prediction_uncertainty import load_uncertainty, stored_prediction
from torchcal.stages.store import load_model

OPSET = 17
MANIFEST_FORMAT = "torchcal-compensator/1"
GRAPHS = {
    "compensator": ("compensator.onnx", torch.float64, "q_nominal", "q_corrected"),
    "compensator_f32": ("compensator_f32.onnx", torch.float32, "q_nominal", "q_corrected"),
    "monitor": ("monitor.onnx", torch.float64, "q", "tcp_error_m"),
    "monitor_f32": ("monitor_f32.onnx", torch.float32, "q", "tcp_error_m"),
}
BUDGET_POSES = 10_000
WRENCH_INPUT = "wrench"
"""Name of the second input of graphs with a stiffness stage."""
DEFAULT_BUDGET_WRENCH = {"max_force_n": 300.0, "max_torque_nm": 30.0}
SOLVER_DEFAULT, SOLVER_PORTABLE = "inverse", "gauss_jordan"
"""The compensator's 6x6 solve: onnxruntime's contrib ``Inverse`` (default) or, with
``portable=True``, an unrolled elimination of standard ONNX operators for other runtimes."""


def onnx_bytes(
    module: torch.nn.Module,
    n_joints: int,
    dtype: torch.dtype,
    input_name: str,
    output_name: str,
    *,
    wrench_input: str | None = None,
    extra_outputs: tuple[str, ...] = (),
) -> bytes:
    """Serialize ``module`` to ONNX (opset :data:`OPSET`, dynamic batch axis) in memory.

    ``wrench_input`` names a second ``(batch, 6)`` input (graphs with a stiffness stage);
    ``extra_outputs`` names outputs after the first (the compensator's ``residual``).

    The TorchScript exporter (``dynamo=False``) is used: the dynamo exporter needs onnxscript,
    which a calibration PC may not have, and the graphs hold no data-dependent control flow.
    onnxruntime's contrib domain is declared for the compensator's ``Inverse`` node; a graph
    without one does not list it.
    """
    if isinstance(module, CompensatorWithResidual):  # its steps are Loops that stop at convergence
        from torchcal.compensate.loop_graph import compensator_model

        return compensator_model(module.graph, n_joints, input_name, (output_name, *extra_outputs), wrench_input=wrench_input,
                                 opset=OPSET, contrib=uses_contrib_inverse(module)).SerializeToString()
    buffer = io.BytesIO()
    example = torch.zeros(2, n_joints, dtype=dtype)
    outputs = [output_name, *extra_outputs]
    args: tuple[torch.Tensor, ...] = (example,)
    names = [input_name]
    axes = {name: {0: "batch"} for name in (input_name, *outputs)}
    if wrench_input is not None:
        args, names = (example, torch.zeros(2, 6, dtype=dtype)), [input_name, wrench_input]
        axes[wrench_input] = {0: "batch"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's deprecation notices, not about this graph
        torch.onnx.export(
            module.eval(),
            args,
            buffer,  # type: ignore[arg-type]  # the TorchScript exporter writes to a file object; the stub says paths only
            dynamo=False,
            opset_version=OPSET,
            input_names=names,
            output_names=outputs,
            dynamic_axes=axes,
            do_constant_folding=True,
            # declared only where a node uses it, so a portable graph loads in any runtime
            custom_opsets={CONTRIB_DOMAIN: 1} if uses_contrib_inverse(module) else None,
        )
    return buffer.getvalue()


def uses_contrib_inverse(module: torch.nn.Module) -> bool:
    """Whether a graph holds onnxruntime's contrib ``Inverse`` (the compensators' default solves;
    ``module`` may be the exported wrapper :class:`CompensatorWithResidual`)."""
    return getattr(getattr(module, "graph", module), "solver", None) == SOLVER_DEFAULT


def build_graphs(
    stored,
    residual: torch.nn.Module | None = None,
    *,
    use_stored_residual: bool = True,
    wrench_frame: str = "tool",
    iterations: int | None = None,
    portable: bool = False,
    task: str = DEFAULT_TASK,
) -> dict[str, torch.nn.Module]:
    """The four torch modules of :data:`GRAPHS` for a :class:`StoredModel`.

    Each of the model's stages gives its piece (:func:`graph_parts`); the inputs its stages add
    (:func:`graph_inputs`) choose the graph classes (:data:`GRAPH_CLASSES`): with a stiffness
    stage they are the loaded graphs, whose second argument is the wrench in ``wrench_frame``
    (``tool`` or ``base``). ``residual``: a head module in place of the stored one
    (``use_stored_residual=False`` without one: no head). ``task``: ``position`` (position first,
    orientation secondary) or ``pose`` (full 6-D); ``iterations``: Newton steps of the
    compensators (``None``: the task's default); ``portable``: standard ONNX operators only
    (see :data:`SOLVER_PORTABLE`).
    """
    solve: dict[str, Any] = {"iterations": iterations, "task": task,
                             "solver": SOLVER_PORTABLE if portable else SOLVER_DEFAULT}
    inputs = graph_inputs(stored)
    if inputs not in GRAPH_CLASSES:
        raise ModelError(f"{stored.folder}: no exported graph takes the inputs {list(inputs)} of its stages")
    compensator_class, monitor_class = GRAPH_CLASSES[inputs]
    parts = graph_parts(stored, inputs)
    if residual is not None or not use_stored_residual:
        parts["residual"] = residual
    input_options = {"wrench": {"wrench_frame": wrench_frame}}  # what each extra input is given in
    for name in inputs:
        parts.update(input_options.get(name, {}))
    graphs: dict[str, torch.nn.Module] = {}
    for key, (_, dtype, _, _) in GRAPHS.items():
        if key.startswith("compensator"):
            graphs[key] = compensator_class(**parts, dtype=dtype, **solve).eval()
        else:
            graphs[key] = monitor_class(**parts, dtype=dtype).eval()
    return graphs


def compensator_of(graphs: dict[str, torch.nn.Module], key: str = "compensator") -> CompensatorGraph:
    """``graphs[key]``, one of the ``compensator*`` graphs of :func:`build_graphs`."""
    graph = graphs[key]
    if not isinstance(graph, CompensatorGraph):
        raise TypeError(f"graphs[{key!r}] is a {type(graph).__name__}, not a compensator graph")
    return graph


def has_wrench_input(graphs: dict[str, torch.nn.Module]) -> bool:
    """Whether the graphs take the expected wrench as a second input."""
    return WRENCH_INPUT in compensator_of(graphs).inputs


def sample_wrenches(n: int, max_force_n: float, max_torque_nm: float, generator: torch.Generator) -> torch.Tensor:
    """Random wrenches ``(n, 6)`` (N, N m): uniform directions, magnitudes uniform up to the maxima."""
    directions = torch.randn(n, 2, 3, generator=generator, dtype=torch.float64)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    size = torch.rand(n, 2, 1, generator=generator, dtype=torch.float64) * torch.tensor([[max_force_n], [max_torque_nm]])
    return (directions * size).reshape(n, 6)


def budget_wrenches(stored, n: int, generator: torch.Generator) -> torch.Tensor:
    """Wrenches for the float32 budget: up to the largest force and moment of the stiffness data."""
    loads = (stored.stiffness.metadata.get("training_wrench") if stored.stiffness is not None else None) or DEFAULT_BUDGET_WRENCH
    return sample_wrenches(n, loads["max_force_n"], loads["max_torque_nm"], generator)


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


def float32_budget(graphs: dict[str, torch.nn.Module], out_dir: Path, stored, n_poses: int = BUDGET_POSES, seed: int = 0) -> dict:
    """Float32 error of the exported files against the float64 torch graphs, measured in mm.

    Poses: ``n_poses`` uniform within the joint limits. Compensator: 3-D distance between the
    calibrated TCP at the float32 ORT command and at the float64 torch command. Monitor: 3-D
    distance of the predicted errors.
    """
    gen = torch.Generator().manual_seed(seed)
    q = stored.robot.sample_joints(n_poses, gen)
    loaded = has_wrench_input(graphs)
    wrench = budget_wrenches(stored, n_poses, gen) if loaded else None
    args = (q, wrench) if loaded else (q,)
    with torch.no_grad():
        qc64 = graphs["compensator"](*args)
        mon64 = graphs["monitor"](*args)
    w32 = wrench.numpy() if wrench is not None else None
    session = ort_session(out_dir / GRAPHS["compensator_f32"][0])
    qc32 = torch.from_numpy(session.run(None, ort_feeds(session, q.float().numpy(), w32))[0]).double()
    session = ort_session(out_dir / GRAPHS["monitor_f32"][0])
    mon32 = torch.from_numpy(session.run(None, ort_feeds(session, q.float().numpy(), w32))[0]).double()
    model = stored.model
    tcp = lambda qq: model.base_flange_pose(qq, stored.x) @ model.flange_from_tool(stored.x)  # noqa: E731
    d_cmd = (tcp(qc32)[..., :3, 3] - tcp(qc64)[..., :3, 3]).norm(dim=-1) * 1e3
    d_mon = (mon32 - mon64).norm(dim=-1) * 1e3
    budget = {
        "n_poses": n_poses,
        "sampling": f"uniform within joint limits, seed {seed}",
        "compensator_tcp_mm": {"max": float(d_cmd.max()), "p99": float(d_cmd.quantile(0.99)), "median": float(d_cmd.median())},
        "compensator_joint_rad_max": float((qc32 - qc64).abs().max()),
        "monitor_mm": {"max": float(d_mon.max()), "p99": float(d_mon.quantile(0.99)), "median": float(d_mon.median())},
    }
    if loaded:
        budget["wrench_sampling"] = "uniform directions, magnitudes uniform up to the stiffness data's largest force and moment"
    return budget


WRIST_SINGULAR_BELOW = 0.02
"""Wrist stratum of the convergence report: smallest singular value of the last three joints'
angular Jacobian below this (for a spherical wrist ``|sin q5|``: about 1.1 deg from alignment)."""
POSITION_SINGULAR_BELOW_M = 0.01
"""Position-singular stratum: smallest singular value of the TCP position Jacobian below 10 mm/rad."""
SOLVABLE_ABOVE_M = 0.001
"""Poses whose position Jacobian keeps a singular value above 1 mm/rad must be solved to 1 um."""


def singular_values(robot, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(sigma_position, sigma_wrist)`` ``(B,)`` of the nominal robot at ``q``: the smallest singular
    value of the TCP position Jacobian (m/rad) and of the last three joints' angular Jacobian (rad/rad)."""
    model = ErrorModel(robot)
    _, jac = geometric_jacobian(model, q, model.nominal_vector())
    return torch.linalg.svdvals(jac[:, :3, :])[:, -1], torch.linalg.svdvals(jac[:, 3:, -3:])[:, -1]


def wrist_singular_samples(robot, n: int, generator: torch.Generator, degrees: float = 1.0, margin: float = 0.0) -> torch.Tensor:
    """``(n, N)`` joints uniform within the limits (``margin`` rad inside) but the second-to-last
    joint within ``+-degrees`` of zero: the wrist singularity of 6-R wrists and of 7-joint arms."""
    q = robot.sample_joints(n, generator, margin=margin)
    limits = robot.joint_limits.to(torch.float64)
    wrist = (torch.rand(n, generator=generator, dtype=torch.float64) * 2 - 1) * math.radians(degrees)
    q[:, -2] = wrist.clamp(limits[-2, 0], limits[-2, 1])
    return q


def _stratum(miss_mm: torch.Tensor, turn: torch.Tensor, joint: torch.Tensor, solvable: torch.Tensor, out_err_mm: torch.Tensor) -> dict:
    """Summary of one stratum: unsolved position (mm), orientation deviation (rad), joint moves (rad)."""
    n = int(miss_mm.numel())
    if n == 0:
        return {"n_poses": 0}
    return {
        "n_poses": n,
        "unsolved_tcp_mm": {"median": float(miss_mm.median()), "p99": float(miss_mm.quantile(0.99)), "max": float(miss_mm.max())},
        "share_within_1um": float((miss_mm <= 1e-3).double().mean()),
        "n_solvable": int(solvable.sum()),
        "solvable_share_within_1um": float((miss_mm[solvable] <= 1e-3).double().mean()) if bool(solvable.any()) else None,
        "orientation_deviation_rad": {"median": float(turn.median()), "p99": float(turn.quantile(0.99)), "max": float(turn.max())},
        "largest_joint_correction_rad": float(joint.max()),
        "residual_output_error": {"position_mm_max": float(out_err_mm.max())},
    }


def convergence_report(graphs: dict[str, torch.nn.Module], stored, n_poses: int = BUDGET_POSES, seed: int = 1) -> dict:
    """What the float64 compensator's commands reach, over the joint range and near singularities.

    Poses: ``n_poses`` uniform within the joint limits, and as many again with the second-to-last
    joint within +-1 deg (the wrist singularity of 6-R wrists and of 7-joint arms; with the
    budget's wrenches for a loaded model). For each command: the position the steps leave
    unsolved, ``|p_nom(q_c) + monitor(q_c) - p_nom(q_t)|`` (mm, through the monitor
    graph, and compared with the compensator's own ``residual`` output), and the orientation
    deviation of the calibrated tool from the nominal target (rad, the ``residual`` output: the
    compensator computes it through the kinematics at ``q_c``). Strata: all uniform poses; wrist
    singular (:data:`WRIST_SINGULAR_BELOW`); position singular (:data:`POSITION_SINGULAR_BELOW_M`).
    A pose counts as solvable where the position Jacobian's smallest singular value exceeds
    :data:`SOLVABLE_ABOVE_M`.
    """
    gen = torch.Generator().manual_seed(seed)
    robot = stored.robot
    uniform = robot.sample_joints(n_poses, gen)
    q = torch.cat([uniform, wrist_singular_samples(robot, n_poses, gen)])
    graph = compensator_of(graphs)
    wrench = budget_wrenches(stored, len(q), gen) if has_wrench_input(graphs) else None
    with torch.no_grad():
        q_c, residual = graph.solve(q, wrench)
    miss = unsolved_distance_m(graphs, robot, q, q_c, wrench) * 1e3
    turn = residual[:, 1]
    out_err = (residual[:, 0] * 1e3 - miss).abs()
    joint = (q_c - q).abs().amax(-1)
    sigma_p, sigma_w = singular_values(robot, q)
    solvable = sigma_p > SOLVABLE_ABOVE_M
    parts = {
        "uniform": torch.arange(len(q)) < n_poses,
        "wrist_singular": sigma_w < WRIST_SINGULAR_BELOW,
        "position_singular": sigma_p < POSITION_SINGULAR_BELOW_M,
    }
    strata = {name: _stratum(miss[m], turn[m], joint[m], solvable[m], out_err[m]) for name, m in parts.items()}
    return {
        "n_poses": n_poses,
        "sampling": (f"uniform within joint limits (seed {seed}), and {n_poses} more with joint {robot.dof - 1} "
                     "within +-1 deg; strata by the nominal robot's singular values"),
        "task": graph.task,
        "iterations": graph.iterations,
        "thresholds": {"wrist_singular_below": WRIST_SINGULAR_BELOW, "position_singular_below_m_per_rad": POSITION_SINGULAR_BELOW_M,
                       "solvable_above_m_per_rad": SOLVABLE_ABOVE_M},
        "strata": strata,
        # the uniform stratum's headline figures, where older readers look for them
        "unsolved_tcp_mm": {**strata["uniform"]["unsolved_tcp_mm"], "p90": float(miss[parts["uniform"]].quantile(0.9))},
        "share_within_1um": strata["uniform"]["share_within_1um"],
        "largest_joint_correction_rad": strata["uniform"]["largest_joint_correction_rad"],
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
) -> dict:
    """Export the compensator of a model folder; returns the manifest (also written to disk).

    ``tcp_mm`` / ``tcp_rpy_deg``: the production TCP in the flange frame (mm, fixed-axis XYZ deg;
    default: the flange), the point the compensator serves (:mod:`torchcal.compensate.production_tcp`),
    stated in the manifest's ``tcp``; the calibration's measured point (the reflector) is not its target.
    ``allow_large_corrections``: export even when a joint correction or the tool orientation
    deviation exceeds the stated limits (otherwise refused).

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
                            portable=portable, task=task, tcp=tcp, allow_large_corrections=allow_large_corrections)


def _export_into(out_dir: Path, model_dir: Path, stored, *, wrench_frame: str, iterations: int | None,
                 portable: bool, task: str, tcp: dict | None = None, allow_large_corrections: bool = True) -> dict:
    """Write the export files of ``stored`` into ``out_dir`` (a staging folder); returns the manifest."""
    graphs = build_graphs(stored, wrench_frame=wrench_frame, iterations=iterations, portable=portable, task=task)
    extent = {}
    if not has_wrench_input(graphs):
        if stored.training_q is not None and len(_regular(stored.robot, stored.training_q)):
            extent["training poses"] = correction_extent(compensator_of(graphs), _regular(stored.robot, stored.training_q))
        extent["joint range"] = correction_extent(
            compensator_of(graphs), _regular(stored.robot, stored.robot.sample_joints(2000, torch.Generator().manual_seed(2))))
    exceeded = check_corrections(extent, allow_large_corrections)
    loaded = has_wrench_input(graphs)
    robot = stored.robot
    files, digests = {}, {}
    for key, (name, dtype, input_name, output_name) in GRAPHS.items():
        is_compensator = key.startswith("compensator")
        module = CompensatorWithResidual(compensator_of(graphs, key)) if is_compensator else graphs[key]
        data = onnx_bytes(module, robot.dof, dtype, input_name, output_name, wrench_input=WRENCH_INPUT if loaded else None,
                          extra_outputs=(RESIDUAL_OUTPUT,) if is_compensator else ())
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
        "training_data": {"sha256": meta.get("data", {}).get("sha256"), "n_poses": meta.get("data", {}).get("n_poses")},
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


def _regular(robot, q: torch.Tensor) -> torch.Tensor:
    """``q`` less the poses near a singularity (the convergence report's strata): there any
    compensator's step is large by the geometry, not by the model."""
    sigma_p, sigma_w = singular_values(robot, q.to(torch.float64))
    return q[(sigma_p >= POSITION_SINGULAR_BELOW_M) & (sigma_w >= WRIST_SINGULAR_BELOW)]


def _correction_limits() -> dict:
    return {"largest_joint_correction_deg": MAX_JOINT_CORRECTION_DEG, "largest_tool_rotation_deg": MAX_TOOL_ROTATION_DEG,
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


def _convergence_text(manifest: dict) -> str:
    """The README's paragraph on what the fixed steps reach, stratum by stratum."""
    conv = manifest["convergence"]
    strata = conv["strata"]
    if conv["task"] == "position":
        what = ("It puts the TCP **position** on the target first and turns the tool toward the nominal orientation only as "
                "far as the position leaves room: near a wrist singularity the orientation may stay off by the deviation "
                "in the `residual` output.")
    else:
        what = ("It solves the full 6-D pose; near singular poses the damping keeps the correction small instead of exact, "
                "for the position too.")
    lines = [(f"The compensator runs at most {conv['iterations']} Newton steps, each pose until it has converged (task "
              f"`{conv['task']}`). {what} Every step moves a joint by at most "
              f"{manifest['solver']['max_step_rad']:.2f} rad and every iterate stays within the joint limits."), "",
             "| poses | n | within 1 um | within 1 um where solvable | unsolved p99 / max (mm) | orientation deviation p99 / max (rad) |",
             "| --- | --- | --- | --- | --- | --- |"]
    for name, s in strata.items():
        if not s.get("n_poses"):
            continue
        solvable = "n/a" if s["solvable_share_within_1um"] is None else f"{100 * s['solvable_share_within_1um']:.1f} % of {s['n_solvable']}"
        lines.append(f"| {name.replace('_', ' ')} | {s['n_poses']} | {100 * s['share_within_1um']:.1f} % | {solvable} | "
                     f"{s['unsolved_tcp_mm']['p99']:.1e} / {s['unsolved_tcp_mm']['max']:.1e} | "
                     f"{s['orientation_deviation_rad']['p99']:.1e} / {s['orientation_deviation_rad']['max']:.1e} |")
    t = conv["thresholds"]
    lines += ["", (f"Solvable: the position Jacobian's smallest singular value above {t['solvable_above_m_per_rad'] * 1e3:.0f} mm/rad; "
                   f"wrist singular: the last three joints' angular Jacobian below {t['wrist_singular_below']}; position singular: "
                   f"below {t['position_singular_below_m_per_rad'] * 1e3:.0f} mm/rad. Sampling: {conv['sampling']}.")]
    return "\n".join(lines)


def _expected_line(manifest: dict) -> str:
    expected = manifest.get("expected_accuracy_95")
    if not expected:
        return "Expected accuracy: not calibrated (the model was fitted with `uncertainty=none`)."
    return (f"Expected accuracy: 95 % of TCP position errors below {expected['p95_mm']:.3f} mm at "
            f"{expected['where'].split(';')[0]} ({expected['method']}, {expected['protocol']}).")


def readme_text(manifest: dict, stage_sections: Sequence[str] = ()) -> str:
    """The integrator's README of an exported folder; ``stage_sections``: the stages' own sections
    (:meth:`~torchcal.stages.base.ModelStage.readme_section`), after the files' table."""
    budget = manifest["float32_error_budget"]
    joints = ", ".join(manifest["joint_names"])
    residual = "yes" if manifest["stages"]["residual"] else "no"
    stiffness = "yes" if manifest["stages"]["stiffness"] else "no"
    joint = ", ".join(k.replace("_", " ") for k in METADATA_KEYS.values() if manifest["stages"].get(k)) or "none"
    wrench = manifest.get("wrench")
    n = manifest["n_joints"]
    extra = f", `{wrench['name']}` (batch, 6)" if wrench else ""
    load = "".join(f"\n{section}" for section in stage_sections)
    return f"""# Compensator for {manifest['robot']}

Exported by torchcal {manifest['versions']['torchcal']} (ONNX opset {manifest['opset']}).
Stages: geometry yes, learned residual {residual}, stiffness {stiffness}, joint-space errors {joint}.
{_expected_line(manifest)}

## Files

| file | input | output |
| --- | --- | --- |
| `compensator.onnx` (float64), `compensator_f32.onnx` (float32) | `q_nominal` (batch, {n}), rad{extra} | `q_corrected` (batch, {n}), rad; `residual` (batch, 2): remaining position error, m, and orientation deviation, rad |
| `monitor.onnx` (float64), `monitor_f32.onnx` (float32) | `q` (batch, {n}), rad{extra} | `tcp_error_m` (batch, 3), m, robot base frame |

Joint order: {joints}. Angles in **radians** in and out (convert degrees before the call).
{load}
## Use

Give the compensator the joint command the controller computed with its nominal kinematics; send
the first output to the drives instead. The real robot then puts its TCP where the nominal model
believed it would be, as far as the calibration knows the robot. The second output, `residual`,
says per command how far the model's TCP still is from that target (m: above your tolerance, the
command was not solved, e.g. at a position singularity) and how far the tool is turned from the
nominal orientation (rad).
The monitor graph predicts, for any joint vector, where the real TCP lies relative to the nominal
one (`real - nominal`, m, base frame).

{_convergence_text(manifest)}
Runtime: {manifest['runtime']}.

Check `sha256` in `manifest.json` before loading (`torchcal.compensate.runtime.CompensatorRuntime`
does; it needs only onnxruntime and numpy). Run single poses with `intra_op_num_threads=1`.

## Accuracy of float32

Measured at export on {budget['n_poses']} random poses within the joint limits, against the float64
graph: compensated TCP within {budget['compensator_tcp_mm']['max']:.2e} mm (max), monitor within
{budget['monitor_mm']['max']:.2e} mm (max). Use the float64 files where the controller allows it.
"""


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
    return result
