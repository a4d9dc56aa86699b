"""The compensator as one ONNX graph whose Newton steps are ``Loop`` s that stop at convergence.

The TorchScript exporter traces: a Python loop becomes a fixed unrolled sequence. The compensator
instead steps each pose only until it has converged (one or two steps almost everywhere, up to
the graph's most near singularities and joint limits), so its parts are traced one by one and
assembled here into one ONNX graph::

    start(q_nominal[, wrench])           -> weights, before, q, J^T, error
    for each phase (mixed steps, then position-only steps):
        score(error) -> score, pending
        Loop(most steps, pending, q, J^T, error, score): iterate(...) -> pending, q, J^T, error, score
    finish(q_nominal, before, q, error)  -> q_corrected, residual

The same parts run in torch (:meth:`CompensatorGraph.solve
<torchcal.compensate.compensator.CompensatorGraph.solve>`), so the torch graph is the reference of
the ONNX one step for step. A ``Loop`` body reads the constants of its iteration (the target's
``weights``, the wrench) from the enclosing graph by name, as ONNX allows.
"""

from __future__ import annotations

import io
import warnings

import torch
from torch import nn

from torchcal.compensate.compensator import CompensatorGraph
from torchcal.compensate.linalg import CONTRIB_DOMAIN

STATE = ("q", "jac_t", "error", "score")
"""What a ``Loop`` carries from one step to the next: command, ``J^T``, error, convergence score."""


class _Part(nn.Module):
    """One traced part of a compensator: a bound method called with tensors only."""

    def __init__(self, graph: CompensatorGraph, fn) -> None:
        super().__init__()
        self.graph = graph
        self.fn = fn

    def forward(self, *args):
        return self.fn(*args)


def _export(module: nn.Module, args: tuple, inputs: list[str], outputs: list[str], batch_inputs: list[str],
            batch_outputs: list[str], opset: int, contrib: bool):
    """``module`` traced to an ONNX ``ModelProto`` with the given input and output names."""
    import onnx

    buffer = io.BytesIO()
    axes = {name: {0: "batch"} for name in (*batch_inputs, *batch_outputs)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's deprecation notices, not about this graph
        torch.onnx.export(module.eval(), args, buffer, dynamo=False, opset_version=opset,  # type: ignore[arg-type]
                          input_names=inputs, output_names=outputs, dynamic_axes=axes, do_constant_folding=True,
                          custom_opsets={CONTRIB_DOMAIN: 1} if contrib else None)
    model = onnx.load_from_string(buffer.getvalue())
    got = [o.name for o in model.graph.output]
    if got != outputs:  # the exporter renames an output that is another output or an input
        raise RuntimeError(f"traced part has outputs {got}, expected {outputs}")
    return model.graph


def _rename(graph, prefix: str, keep: dict[str, str]) -> None:
    """Prefix every tensor name of ``graph`` (in place) except those in ``keep`` (mapped to their value)."""

    def name(n: str) -> str:
        if n == "":
            return n  # an omitted optional input
        return keep.get(n, prefix + n)

    import onnx

    for node in graph.node:
        node.input[:] = [name(n) for n in node.input]
        node.output[:] = [name(n) for n in node.output]
        node.name = prefix + node.name
        for attribute in node.attribute:  # a subgraph reads the enclosing graph's names
            if attribute.type == onnx.AttributeProto.GRAPH:
                _rename(attribute.g, prefix, keep)
    for collection in (graph.input, graph.output, graph.value_info):
        for v in collection:
            v.name = name(v.name)
    for t in graph.initializer:
        t.name = name(t.name)


def compensator_model(graph: CompensatorGraph, n_joints: int, input_name: str, output_names: tuple[str, ...], *,
                      wrench_input: str | None = None, opset: int = 17, contrib: bool = True):
    """The ONNX ``ModelProto`` of ``graph``: ``(input_name[, wrench_input]) -> output_names`` (command, residual)."""
    import onnx
    from onnx import TensorProto, helper

    graph = graph.eval()
    dtype = graph.dtype
    example = torch.linspace(-0.5, 0.5, 2 * n_joints, dtype=dtype).reshape(2, n_joints)
    wrench = torch.zeros(2, 6, dtype=dtype) if wrench_input is not None else None
    with torch.no_grad():
        q64, w64 = graph.widen(example, wrench)
        weights, before, q, jac_t, error = graph.start(q64, w64)
    loaded = wrench_input is not None
    nodes, initializers = [], []

    def add(part_graph) -> None:
        nodes.extend(part_graph.node)
        initializers.extend(part_graph.initializer)

    # start: the graph inputs in, the first iterate out (a float32 graph widens its inputs here)
    start_in = [input_name] + ([wrench_input] if wrench_input is not None else [])
    start_out = ["weights", "q_0", "jac_t_0", "error_0"] + (["wrench_wide"] if loaded else [])

    def start_fn(q_in, w_in=None):
        q_w, w_w = graph.widen(q_in, w_in)
        w_b, _, q_0, j_0, e_0 = graph.start(q_w, w_w)  # ``before`` is error_0 (the loops leave it as it is)
        return (w_b, q_0, j_0, e_0) + ((w_w,) if loaded else ())

    part = _export(_Part(graph, start_fn), (example,) + ((wrench,) if loaded else ()), start_in, start_out,
                   start_in, start_out, opset, False)
    _rename(part, "start/", {n: n for n in start_in + start_out})
    add(part)
    outer = ["weights"] + (["wrench_wide"] if loaded else [])
    state_args = (q, jac_t, error)
    index = 0
    for phase, (orientation, steps) in enumerate(graph.phases):
        # the phase's convergence score of the incoming error, and whether any pose needs a step
        def score_fn(e, orientation=orientation):
            s = graph.score(e, orientation)
            return s, graph.pending(s)

        names_in = [f"error_{index}"]
        names_out = [f"score_{index}", f"pending_{index}"]
        part = _export(_Part(graph, score_fn), (error,), names_in, names_out, names_in, names_out[:1], opset, False)
        _rename(part, f"score{phase}/", {n: n for n in names_in + names_out})
        add(part)
        with torch.no_grad():
            score = graph.score(error, orientation)

        # the body: carried state in, (pending, state) out; the target and wrench from the enclosing graph
        def body_fn(q_b, j_b, e_b, s_b, w_b, wr_b=None, orientation=orientation):
            return graph.iterate(q_b, j_b, e_b, s_b, w_b, wr_b, orientation)

        body_in = [f"{s}_in" for s in STATE] + outer
        body_out = ["pending_out"] + [f"{s}_out" for s in STATE]
        args = (*state_args, score, weights) + ((w64,) if loaded else ())
        body = _export(_Part(graph, body_fn), args, body_in, body_out, body_in, body_out[1:], opset, contrib)
        keep = {n: n for n in body_in + body_out}
        keep.update({n: n for n in outer})  # outer-scope names stay as they are
        _rename(body, f"phase{phase}/", keep)
        carried = [v for v in body.input if v.name not in outer]
        del body.input[:]
        body.input.extend([helper.make_tensor_value_info("iteration", TensorProto.INT64, []),
                           helper.make_tensor_value_info("pending_in", TensorProto.BOOL, []), *carried])
        body.name = f"phase{phase}"
        most = helper.make_tensor(f"most_steps_{phase}", TensorProto.INT64, [], [steps])
        initializers.append(most)
        loop_in = [f"most_steps_{phase}", f"pending_{index}"] + [f"{s}_{index}" for s in STATE]
        # the score a loop ends with is the last phase's; the next phase scores the error anew
        loop_out = [f"{s}_{index + 1}" for s in STATE[:-1]] + [f"score_end_{index + 1}"]
        nodes.append(helper.make_node("Loop", loop_in, loop_out, name=f"steps_{phase}", body=body))
        index += 1
    # finish: the command, or the nominal one where the steps ended further from the target
    finish_in = ["q_0", "error_0", f"q_{index}", f"error_{index}"]

    def finish_fn(q_nom, bef, q_last, e_last):
        return graph.narrow(*graph.finish(q_nom, bef, q_last, e_last))

    part = _export(_Part(graph, finish_fn), (q64, before, q, error), finish_in, list(output_names), finish_in,
                   list(output_names), opset, False)
    _rename(part, "finish/", {n: n for n in finish_in + list(output_names)})
    add(part)

    onnx_type = TensorProto.DOUBLE if dtype == torch.float64 else TensorProto.FLOAT
    inputs = [helper.make_tensor_value_info(input_name, onnx_type, ["batch", n_joints])]
    if wrench_input is not None:
        inputs.append(helper.make_tensor_value_info(wrench_input, onnx_type, ["batch", 6]))
    outputs = [helper.make_tensor_value_info(output_names[0], onnx_type, ["batch", n_joints]),
               helper.make_tensor_value_info(output_names[1], onnx_type, ["batch", 2])]
    main = helper.make_graph(nodes, "compensator", inputs, outputs, initializer=initializers)
    imports = [helper.make_opsetid("", opset)] + ([helper.make_opsetid(CONTRIB_DOMAIN, 1)] if contrib else [])
    model = helper.make_model(main, opset_imports=imports, producer_name="torchcal")
    model.ir_version = 8
    onnx.checker.check_model(model)
    return model


def with_float32_interface(model):
    """The float64 compensator ``model`` (a ``ModelProto`` of :func:`compensator_model`) behind a float32
    interface: its inputs cast to float64 on the way in, its outputs to float32 on the way out.

    This is what the graph of the same parts traced with ``dtype=float32`` computes (a float32
    compensator widens its inputs and narrows its outputs and is float64 in between:
    :meth:`CompensatorGraph.widen`, :meth:`CompensatorGraph.narrow`), without tracing it again.
    """
    import onnx
    from onnx import TensorProto, helper

    wide = onnx.ModelProto()
    wide.CopyFrom(model)
    graph = wide.graph
    inputs = {v.name: f"{v.name}/float64" for v in graph.input}
    outputs = {v.name: f"{v.name}/float64" for v in graph.output}
    _rename_uses(graph, inputs)
    for node in graph.node:
        node.output[:] = [outputs.get(n, n) for n in node.output]
    body = list(graph.node)
    del graph.node[:]
    graph.node.extend([helper.make_node("Cast", [n], [w], to=TensorProto.DOUBLE, name=f"widen/{n}") for n, w in inputs.items()])
    graph.node.extend(body)
    graph.node.extend([helper.make_node("Cast", [w], [n], to=TensorProto.FLOAT, name=f"narrow/{n}") for n, w in outputs.items()])
    for v in (*graph.input, *graph.output):
        v.type.tensor_type.elem_type = TensorProto.FLOAT
    onnx.checker.check_model(wide)
    return wide


def _rename_uses(graph, names: dict[str, str]) -> None:
    """Every node of ``graph`` and of its subgraphs reads ``names[n]`` where it read ``n`` (in place)."""
    import onnx

    for node in graph.node:
        node.input[:] = [names.get(n, n) for n in node.input]
        for attribute in node.attribute:
            if attribute.type == onnx.AttributeProto.GRAPH:
                _rename_uses(attribute.g, names)
