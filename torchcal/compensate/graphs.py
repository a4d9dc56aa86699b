"""The exported graphs of a model folder, built from its stages, and their ONNX bytes.

:func:`build_graphs` takes each stage's piece (:func:`torchcal.compensate.compensator.graph_parts`)
and the graph classes the stages' extra inputs choose; :func:`onnx_bytes` traces one graph to a
single-file ONNX model (opset :data:`OPSET`). The files and their units: :mod:`torchcal.compensate.export`.
"""

from __future__ import annotations

import io
import math
import warnings
from typing import Any

import torch

from torchcal.compensate.compensator import (
    DEFAULT_TASK,
    GRAPH_CLASSES,
    CompensatorGraph,
    CompensatorWithResidual,
    graph_inputs,
    graph_parts,
)
from torchcal.compensate.linalg import CONTRIB_DOMAIN
from torchcal.core.errors import ModelError, TorchcalError

OPSET = 17
GRAPHS = {
    "compensator": ("compensator.onnx", torch.float64, "q_nominal", "q_corrected"),
    "compensator_f32": ("compensator_f32.onnx", torch.float32, "q_nominal", "q_corrected"),
    "monitor": ("monitor.onnx", torch.float64, "q", "tcp_error_m"),
    "monitor_f32": ("monitor_f32.onnx", torch.float32, "q", "tcp_error_m"),
}
WRENCH_INPUT = "wrench"
"""Name of the second input of graphs with a stiffness stage."""
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


def float32_compensator_bytes(compensator_f64: bytes) -> bytes:
    """The float32 compensator file from the float64 one's bytes (:func:`onnx_bytes` of
    ``compensator``): the same graph behind float32 inputs and outputs, as tracing the float32
    graph gives it (:func:`~torchcal.compensate.loop_graph.with_float32_interface`)."""
    import onnx

    from torchcal.compensate.loop_graph import with_float32_interface

    return with_float32_interface(onnx.load_from_string(compensator_f64)).SerializeToString()


def uses_contrib_inverse(module: torch.nn.Module) -> bool:
    """Whether a graph holds onnxruntime's contrib ``Inverse`` (the compensators' default solves;
    ``module`` may be the exported wrapper :class:`CompensatorWithResidual`)."""
    return getattr(getattr(module, "graph", module), "solver", None) == SOLVER_DEFAULT


def check_tool_length(tool_length_mm: float) -> None:
    """Refuse a tool length (``--tool-length-mm``, mm) that is not a finite number >= 0."""
    if not (math.isfinite(tool_length_mm) and tool_length_mm >= 0):
        raise TorchcalError(f"--tool-length-mm must be a finite length >= 0 mm, got {tool_length_mm:g}")


def build_graphs(
    stored,
    residual: torch.nn.Module | None = None,
    *,
    use_stored_residual: bool = True,
    wrench_frame: str = "tool",
    iterations: int | None = None,
    portable: bool = False,
    task: str = DEFAULT_TASK,
    tool_length: float = 0.0,
) -> dict[str, torch.nn.Module]:
    """The four torch modules of :data:`GRAPHS` for a :class:`StoredModel`.

    Each of the model's stages gives its piece (:func:`graph_parts`); the inputs its stages add
    (:func:`graph_inputs`) choose the graph classes (:data:`GRAPH_CLASSES`): with a stiffness
    stage they are the loaded graphs, whose second argument is the wrench in ``wrench_frame``
    (``tool`` or ``base``). ``residual``: a head module in place of the stored one
    (``use_stored_residual=False`` without one: no head). ``task``: ``position`` (position first,
    orientation secondary) or ``pose`` (full 6-D); ``iterations``: Newton steps of the
    compensators (``None``: the task's default); ``portable``: standard ONNX operators only
    (see :data:`SOLVER_PORTABLE`); ``tool_length``: m, the compensators keep the nominal command
    where the corrected one leaves a point that far beyond the TCP further off
    (:class:`~torchcal.compensate.compensator.CompensatorGraph`).
    """
    solve: dict[str, Any] = {"iterations": iterations, "task": task, "tool_length": tool_length,
                             "solver": SOLVER_PORTABLE if portable else SOLVER_DEFAULT}
    stages = stored.stages()
    inputs = graph_inputs(stages)
    if inputs not in GRAPH_CLASSES:
        raise ModelError(f"{stored.folder}: no exported graph takes the inputs {list(inputs)} of its stages")
    compensator_class, monitor_class = GRAPH_CLASSES[inputs]
    parts = graph_parts(stages, inputs)
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
