"""Latency and throughput of the exported compensator (onnxruntime) against torch eager.

Usage: python scripts/bench_onnx.py [--model DIR] [--out docs/bench_onnx] [--quick]

Without ``--model`` a twin is calibrated on the spot (geometry only). Measures, for the
exported graphs (compensator and monitor in float64 and float32) and for compensator variants
in the same run (:data:`VARIANTS`: the portable Gauss-Jordan solve, 1 and 2 Newton steps):

* operators per graph (nodes that run; constants are folded at load), and for the default
  compensator the nodes per part after onnxruntime's own optimization (start, each phase's
  ``Loop`` body, finish) with the steps the poses take (uniform and wrist-singular poses);
* single-sample latency (batch 1), median and p99 over many calls, onnxruntime with
  ``intra_op_num_threads=1`` (one core, as on a controller), all graphs round-robin so they share
  the load, beside a one-node graph (the cost of a call itself); torch eager with one thread;
* the nodes onnxruntime runs for one pose (its profiler) against a chain of as many trivial nodes
  in warm blocks: what the per-node cost alone allows, and the node count the target leaves;
* batch throughput (poses/s) at a large batch, onnxruntime on one thread and on all cores,
  torch eager on all cores;
* convergence of the compensator against its iteration count (worst and 99th-percentile TCP
  residual over random poses within the joint limits);
* the default compensator called the ways a controller can (``InferenceSession.run``, IO binding,
  the runner's checked ``correct`` and per-cycle ``correct_one``, session options) and over pose
  sets (one pose, 200 uniform poses, 200 wrist-singular poses), all against the one-node floor
  of the same round-robin.

Writes ``OUT.json`` and ``OUT.md`` (atomically).
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np


def _latency(fn, calls: int, warmup: int = 200) -> dict:
    for _ in range(warmup):
        fn()
    times = np.empty(calls)
    for i in range(calls):
        t0 = time.perf_counter_ns()
        fn()
        times[i] = time.perf_counter_ns() - t0
    us = times / 1e3
    return {"median_us": float(np.median(us)), "p99_us": float(np.percentile(us, 99)), "calls": calls}


def _throughput(fn, batch: int, repeats: int) -> dict:
    fn()
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        rates.append(batch / (time.perf_counter() - t0))
    return {"median_poses_per_s": float(np.median(rates)), "batch": batch, "repeats": repeats}


def machine_info(load_before: float) -> dict:
    """The machine and versions a benchmark ran on, with the 1-minute load before (``load_before``) and now."""
    import onnxruntime as ort
    import torch

    return {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(), "python": platform.python_version(),
            "onnxruntime": ort.__version__, "torch": torch.__version__,
            "load_average_1min": {"before": load_before, "after": os.getloadavg()[0]}}


def _session(path: Path, threads: int | None, **config):
    """A CPU session; ``config``: ``spinning`` (bool), ``mem_pattern`` (bool)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    if "spinning" in config:
        options.add_session_config_entry("session.intra_op.allow_spinning", "1" if config["spinning"] else "0")
    if "mem_pattern" in config:
        options.enable_mem_pattern = bool(config["mem_pattern"])
    options.log_severity_level = 3
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    if threads is not None:
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def bench_arguments(argv: list[str] | None, description: str, out: str) -> argparse.Namespace:
    """The options both ONNX benchmarks take: ``--model``, ``--out`` (default ``out``), ``--quick``."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--model", help="model folder (default: calibrate a twin: seed 0, 300 poses, geometry only)")
    parser.add_argument("--out", default=out, help="output path without extension")
    parser.add_argument("--quick", action="store_true", help="fewer calls (smoke run)")
    return parser.parse_args(argv)


def benchmark_pose(robot, rng: np.random.Generator | None = None) -> np.ndarray:
    """``(1, N)`` rad: the single pose whose latency both ONNX benchmarks time, uniform within the limits, the
    first draw of ``rng`` (default: a fresh ``default_rng(0)``, as every run of either benchmark starts)."""
    rng = np.random.default_rng(0) if rng is None else rng
    limits = robot.joint_limits.numpy()
    return limits[:, 0] + rng.random((1, robot.dof)) * (limits[:, 1] - limits[:, 0])


def _model_dir(tmp: Path) -> Path:
    import torch

    from torchcal.config.schema import FitConfig
    from torchcal.sim.twin import Twin, TwinConfig
    from torchcal.stages.geometry import fit, save_fit

    twin = Twin.create(TwinConfig(seed=0))
    train = twin.sample(300, torch.Generator().manual_seed(1))
    result = fit(twin.robot, train, FitConfig(residual="none", gravity_compliance="none", joint_harmonics="none"))
    return save_fit(tmp / "model", twin.robot, train, result, {})


def convergence(stored, n_poses: int, task: str, max_iterations: int = 8) -> list[dict]:
    """TCP position / rotation residual of the float64 compensator against its iteration count.

    Two strata of ``n_poses`` each: uniform within the joint limits, and the same with the
    second-to-last joint within +-1 deg (the wrist singularity). Positions are scored on the
    poses whose position Jacobian keeps a singular value above 1 mm/rad (the solvable ones).
    """
    import torch

    from torchcal.compensate.compensator import CompensatorGraph
    from torchcal.compensate.export_checks import (
        SOLVABLE_ABOVE_M,
        singular_values,
        wrist_singular_samples,
    )
    from torchcal.kinematics.error_model import ErrorModel
    from torchcal.kinematics.ik import pose_error

    gen = torch.Generator().manual_seed(5)
    uniform = stored.robot.sample_joints(n_poses, gen)
    wrist = wrist_singular_samples(stored.robot, n_poses, gen)
    base_model = ErrorModel(stored.robot)
    rows = []
    for stratum, q in (("uniform", uniform), ("|q_(N-1)| < 1 deg", wrist)):
        target = stored.robot.flange_pose(q).clone()
        target[..., :3, 3] = target[..., :3, :3] @ stored.robot.tool + target[..., :3, 3]
        solvable = singular_values(stored.robot, q)[0] > SOLVABLE_ABOVE_M
        for n in range(1, max_iterations + 1):
            with torch.no_grad():
                q_c = CompensatorGraph(stored.model, stored.x, task=task, iterations=n)(q)
            e = pose_error(target, base_model.tcp_pose(q_c, stored.x))
            p, r = e[:, :3].norm(dim=-1)[solvable], e[:, 3:].norm(dim=-1)
            rows.append({
                "task": task, "stratum": stratum, "iterations": n, "n_solvable": int(solvable.sum()),
                "position_p50_m": float(p.median()), "position_p99_m": float(p.quantile(0.99)), "position_max_m": float(p.max()),
                "fraction_below_1um": float((p < 1e-6).double().mean()),
                "rotation_p99_rad": float(r.quantile(0.99)),
                "joint_step_max_rad": float((q_c - q).abs().max()),
            })
    return rows


def _opt_level_sessions(path: Path) -> dict:
    """The default compensator under each onnxruntime graph optimization level (one thread)."""
    import onnxruntime as ort

    levels = {"disable_all": ort.GraphOptimizationLevel.ORT_DISABLE_ALL, "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
              "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED, "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL}
    sessions = {}
    for name, level in levels.items():
        options = ort.SessionOptions()
        options.log_severity_level = 3
        options.graph_optimization_level = level
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        sessions[name] = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    return sessions


def _floor_graph(path: Path, n_joints: int) -> None:
    """A one-node graph (``Identity``) with the compensator's input: the cost of a call itself."""
    import onnx
    from onnx import TensorProto, helper

    graph = helper.make_graph([helper.make_node("Identity", ["q_nominal"], ["q_corrected"])], "floor",
                              [helper.make_tensor_value_info("q_nominal", TensorProto.DOUBLE, ["batch", n_joints])],
                              [helper.make_tensor_value_info("q_corrected", TensorProto.DOUBLE, ["batch", n_joints])])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))


def _chain_graph(path: Path, n_nodes: int, n_joints: int) -> None:
    """A graph of ``n_nodes`` trivial nodes in a row (``Sin`` and ``Neg`` in turn) on the compensator's
    input: what a graph of that many nodes costs at least, whatever they compute."""
    import onnx
    from onnx import TensorProto, helper

    names = ["q_nominal"] + [f"t{i}" for i in range(n_nodes - 1)] + ["q_corrected"]
    nodes = [helper.make_node("Sin" if i % 2 == 0 else "Neg", [names[i]], [names[i + 1]]) for i in range(n_nodes)]
    graph = helper.make_graph(nodes, "chain",
                              [helper.make_tensor_value_info("q_nominal", TensorProto.DOUBLE, ["batch", n_joints])],
                              [helper.make_tensor_value_info("q_corrected", TensorProto.DOUBLE, ["batch", n_joints])])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))


def executed_nodes(path: Path, input_name: str, x: np.ndarray) -> int:
    """Nodes onnxruntime runs in one call of the graph at ``path`` on ``x`` (its profiler's kernel
    events; a ``Loop`` or ``If`` counts by the nodes of its bodies that run, not itself)."""
    import json

    import onnxruntime as ort

    with tempfile.TemporaryDirectory() as tmp:
        options = ort.SessionOptions()
        options.log_severity_level = 3
        options.intra_op_num_threads = 1
        options.enable_profiling = True
        options.profile_file_prefix = str(Path(tmp) / "profile")
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        session.run(None, {input_name: x})
        events = json.loads(Path(session.end_profiling()).read_text())
    return sum(1 for e in events if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time")
               and e.get("args", {}).get("op_name") not in ("Loop", "If"))


def _operators(path: Path) -> int:
    """Nodes of a graph that do work at run time (``Constant`` nodes are folded at load), a ``Loop``
    body's counted once (the nodes of one step)."""
    import onnx

    def count(graph) -> int:
        bodies = [a.g for n in graph.node for a in n.attribute if a.type == onnx.AttributeProto.GRAPH]
        return sum(1 for node in graph.node if node.op_type != "Constant") + sum(count(b) for b in bodies)

    return count(onnx.load(str(path)).graph)


def _interleaved_latency(calls_by_name: dict, calls: int, warmup: int = 200) -> dict:
    """Single-call latency of several callables, measured round-robin so they share the same load."""
    for fn in calls_by_name.values():
        for _ in range(warmup):
            fn()
    times = {name: np.empty(calls) for name in calls_by_name}
    for i in range(calls):
        for name, fn in calls_by_name.items():
            t0 = time.perf_counter_ns()
            fn()
            times[name][i] = time.perf_counter_ns() - t0
    return {name: {"median_us": float(np.median(t / 1e3)), "p99_us": float(np.percentile(t / 1e3, 99)), "calls": calls}
            for name, t in times.items()}


def _optimized_parts(path: Path) -> dict:
    """Nodes of a compensator after onnxruntime's optimization (``ORT_ENABLE_ALL``), by part:
    ``start``, ``score`` (before each phase), ``finish``, and each phase's ``Loop`` body (one step)."""
    import onnx
    import onnxruntime as ort

    with tempfile.TemporaryDirectory() as tmp:
        options = ort.SessionOptions()
        options.log_severity_level = 3
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.optimized_model_filepath = str(Path(tmp) / "optimized.onnx")
        ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        model = onnx.load(options.optimized_model_filepath)
    parts: dict[str, int] = {}
    for node in model.graph.node:
        if node.op_type == "Loop":
            parts[f"{node.name} (one step)"] = len(node.attribute[0].g.node)
            continue
        part = node.name.split("/")[0] if "/" in node.name else "other"
        parts[part] = parts.get(part, 0) + 1
    return parts


def steps_taken(graph, q) -> dict:
    """How many steps each pose of ``q`` takes in each phase of ``graph`` (the torch reference of
    the exported Loops): ``{"mixed": (B,), "position": (B,)}`` as lists."""
    import torch

    with torch.no_grad():
        weights, _, q_it, jac_t, error = graph.start(q.to(torch.float64), None)
        taken = {}
        for orientation, most in graph.phases:
            score = graph.score(error, orientation)
            count = torch.zeros(len(q), dtype=torch.long)
            for _ in range(most):
                active = score[:, 0] >= 1.0
                if not bool(active.any()):
                    break
                count += active.long()
                _, q_it, jac_t, error, score = graph.iterate(q_it, jac_t, error, score, weights, None, orientation)
            taken["mixed" if orientation else "position"] = count.tolist()
    return taken


def _histogram(counts: list[int]) -> dict:
    values, number = np.unique(np.asarray(counts), return_counts=True)
    return {int(v): int(n) for v, n in zip(values, number)}


def _cycling(session, name: str, poses: np.ndarray):
    """A call that feeds the next of ``poses`` (one per call, in turn)."""
    rows = [np.ascontiguousarray(p[None]) for p in poses]
    state = {"i": 0}

    def call():
        state["i"] = (state["i"] + 1) % len(rows)
        return session.run(None, {name: rows[state["i"]]})

    return call


def _block_latency(calls_by_name: dict, calls: int, rounds: int = 7) -> dict:
    """Latency of each callable measured in blocks of ``calls`` consecutive calls (warm caches, as a
    controller calling one graph per cycle), the callables in turn for ``rounds`` rounds so that all
    share the machine's load; per callable the medians over the rounds of each block's median and p99."""
    per: dict[str, list[tuple[float, float]]] = {name: [] for name in calls_by_name}
    for _ in range(rounds):
        for name, fn in calls_by_name.items():
            block = _latency(fn, calls, warmup=50)
            per[name].append((block["median_us"], block["p99_us"]))
    return {name: {"median_us": float(np.median([m for m, _ in v])), "p99_us": float(np.median([p for _, p in v])),
                   "calls": calls, "rounds": rounds} for name, v in per.items()}


def _export_tag(options: dict) -> str:
    """Folder name of one export's options (variants with the same options share the export)."""
    return "-".join(f"{k}{v}" for k, v in sorted(options.items())) or "default"


VARIANTS: dict[str, tuple[dict, str, str]] = {
    # key: (export options, graph key inside that export, description)
    "compensator": ({}, "compensator", "float64, position first, at most 6 steps (3 mixed, 3 position-only), stops at convergence (default)"),
    "compensator_f32": ({}, "compensator_f32", "float32 in/out, float64 inside, as the default"),
    "compensator_position_4_steps": ({"iterations": 4}, "compensator", "float64, position first, at most 4 steps"),
    "compensator_1_step": ({"iterations": 1}, "compensator", "float64, position first, at most 1 step (start + one step + finish)"),
    "compensator_pose": ({"task": "pose"}, "compensator", "float64, full 6-D pose, at most 3 steps, onnxruntime Inverse"),
    "compensator_pose_portable": ({"task": "pose", "portable": True}, "compensator",
                                  "float64, full 6-D pose, at most 3 steps, unrolled Gauss-Jordan (standard operators)"),
    "monitor": ({}, "monitor", "float64"),
    "monitor_f32": ({}, "monitor_f32", "float32"),
}


def main(argv: list[str] | None = None) -> int:
    args = bench_arguments(argv, "onnxruntime vs torch eager for the exported compensator", "docs/bench_onnx")

    import torch
    from rich.console import Console

    from torchcal.compensate.export import export_model
    from torchcal.compensate.export_checks import wrist_singular_samples
    from torchcal.compensate.graphs import GRAPHS, build_graphs
    from torchcal.core.io import atomic_write_json, atomic_write_text
    from torchcal.stages.store import load_model

    console = Console()
    load_before = os.getloadavg()
    calls = 500 if args.quick else 5000
    repeats = 3 if args.quick else 5
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        with console.status("[bold]preparing model and exports"):
            model_dir = Path(args.model) if args.model else _model_dir(tmp)
            stored = load_model(model_dir)
            folders, graphs = {}, {}
            for options, _, _ in VARIANTS.values():
                tag = _export_tag(options)
                if tag not in folders:
                    folders[tag] = tmp / tag
                    export_model(model_dir, folders[tag], **options)
                    graphs[tag] = build_graphs(stored, **options)
            _floor_graph(tmp / "floor.onnx", stored.robot.dof)
            # the nodes the default compensator runs for the benchmark pose, and a chain of as many trivial ones
            rng = np.random.default_rng(0)  # the benchmark pose first, then the batches below
            limits = stored.robot.joint_limits.numpy()
            q_one = benchmark_pose(stored.robot, rng)
            n_executed = executed_nodes(folders["default"] / GRAPHS["compensator"][0], GRAPHS["compensator"][2], q_one)
            _chain_graph(tmp / "chain.onnx", n_executed, stored.robot.dof)
        # Latency first, before any multi-threaded work: thread pools that have just run (torch's
        # OpenMP, onnxruntime's intra-op) keep spinning for a while and inflate single calls.
        torch_threads = torch.get_num_threads()
        torch.set_num_threads(1)
        single_calls = {}
        floor = _session(tmp / "floor.onnx", threads=1)
        single_calls["one-node graph (call floor)"] = lambda: floor.run(None, {"q_nominal": q_one})
        floor_alone = _latency(single_calls["one-node graph (call floor)"], calls)  # before anything else runs
        chain = _session(tmp / "chain.onnx", threads=1)
        chain_name = f"chain of {n_executed} trivial nodes"
        single_calls[chain_name] = lambda: chain.run(None, {"q_nominal": q_one})
        for key, (options, graph_key, _) in VARIANTS.items():
            tag = _export_tag(options)
            name, dtype, input_name, _ = GRAPHS[graph_key]
            q1 = np.ascontiguousarray(q_one.astype(np.float64 if dtype == torch.float64 else np.float32))
            single_calls[key] = (lambda s, n, x: lambda: s.run(None, {n: x}))(_session(folders[tag] / name, threads=1), input_name, q1)
        # the default compensator as an integrator would call it: through the checking runner, and
        # with onnxruntime's IO binding (input and output buffers bound once, no per-call dicts)
        from torchcal.compensate.runtime import CompensatorRuntime

        runner = CompensatorRuntime(folders["default"], threads=1)
        q_row = q_one[0].copy()
        single_calls["compensator via CompensatorRuntime.correct"] = lambda: runner.correct(q_row)
        bound_session = _session(folders["default"] / GRAPHS["compensator"][0], threads=1)
        binding = bound_session.io_binding()
        binding.bind_cpu_input(GRAPHS["compensator"][2], np.ascontiguousarray(q_one))
        binding.bind_output(GRAPHS["compensator"][3])
        single_calls["compensator via run_with_iobinding"] = lambda: bound_session.run_with_iobinding(binding)
        single_calls["compensator via CompensatorRuntime.correct_one (bound buffers)"] = lambda: runner.correct_one(q_row)
        for label, config in (("spinning off", {"spinning": False}), ("memory pattern off", {"mem_pattern": False})):
            session = _session(folders["default"] / GRAPHS["compensator"][0], threads=1, **config)
            single_calls[f"compensator, {label}"] = (lambda s, x: lambda: s.run(None, {GRAPHS["compensator"][2]: x}))(
                session, np.ascontiguousarray(q_one))
        # the same graph over pose sets (one pose per call, in turn): what a controller sees along a path
        pose_gen = torch.Generator().manual_seed(9)
        pose_sets = {"200 uniform poses": stored.robot.sample_joints(200, pose_gen),
                     "200 wrist-singular poses (|q_(N-1)| < 1 deg)": wrist_singular_samples(stored.robot, 200, pose_gen)}
        for label, poses in pose_sets.items():
            session = _session(folders["default"] / GRAPHS["compensator"][0], threads=1)
            single_calls[f"compensator, {label}"] = _cycling(session, GRAPHS["compensator"][2], poses.numpy())
        for level, session in _opt_level_sessions(folders["default"] / GRAPHS["compensator"][0]).items():
            single_calls[f"compensator, graph optimization {level}"] = (
                lambda s, x: lambda: s.run(None, {GRAPHS["compensator"][2]: x}))(session, np.ascontiguousarray(q_one))
        console.log("single-sample latency, all graphs round-robin, one thread")
        latency = _interleaved_latency(single_calls, calls)
        console.log("single-sample latency in warm blocks, one thread")
        blocks = _block_latency({k: single_calls[k] for k in (
            "one-node graph (call floor)", chain_name, "compensator", "compensator via CompensatorRuntime.correct",
            "compensator via CompensatorRuntime.correct_one (bound buffers)", "compensator, 200 uniform poses",
            "compensator, 200 wrist-singular poses (|q_(N-1)| < 1 deg)")}, max(100, calls // 10))
        del single_calls
        results = {}
        for key, (options, graph_key, description) in VARIANTS.items():
            tag = _export_tag(options)
            name, dtype, input_name, _ = GRAPHS[graph_key]
            console.log(f"benchmarking {key} ({description})")
            # the compensator is ~30x the work of the monitor: a smaller batch keeps the run short
            batch = (20_000 if args.quick else 200_000) // (10 if graph_key.startswith("compensator") else 1)
            q_batch64 = limits[:, 0] + rng.random((batch, stored.robot.dof)) * (limits[:, 1] - limits[:, 0])
            np_dtype = np.float64 if dtype == torch.float64 else np.float32
            q1 = np.ascontiguousarray(q_one.astype(np_dtype))
            qb = np.ascontiguousarray(q_batch64.astype(np_dtype))
            path = folders[tag] / name
            one = _session(path, threads=1)
            many = _session(path, threads=None)
            module = graphs[tag][graph_key]
            t1, tb = torch.from_numpy(q1), torch.from_numpy(qb)
            entry = {
                "description": description,
                "operators": _operators(path),
                "ort_batch_1thread": _throughput(lambda: one.run(None, {input_name: qb}), batch, repeats),
                "ort_batch_all_threads": _throughput(lambda: many.run(None, {input_name: qb}), batch, repeats),
            }
            with torch.inference_mode():
                torch.set_num_threads(1)
                entry["torch_single_1thread"] = _latency(lambda: module(t1), max(200, calls // 5))
                torch.set_num_threads(torch_threads)
                entry["torch_batch_all_threads"] = _throughput(lambda: module(tb), batch, repeats)
            entry["ort_single_1thread"] = latency[key]
            results[key] = entry
        default_graph = graphs["default"]["compensator"]
        taken = {label: steps_taken(default_graph, poses) for label, poses in pose_sets.items()}
        taken["the single-pose benchmark pose"] = steps_taken(default_graph, torch.from_numpy(q_one))
        parts = {"nodes": _optimized_parts(folders["default"] / GRAPHS["compensator"][0]),
                 "nodes_one_step_graph": _optimized_parts(folders[_export_tag({"iterations": 1})] / GRAPHS["compensator"][0]),
                 "steps": {label: {phase: _histogram(c) for phase, c in t.items()} for label, t in taken.items()}}
        with console.status("[bold]convergence against iteration count"):
            n_conv = 1000 if args.quick else 4000
            conv = convergence(stored, n_conv, "position") + convergence(stored, n_conv, "pose", max_iterations=5)
    report = {
        "machine": machine_info(load_before[0]),
        "model": {"folder": str(model_dir) if args.model else "twin seed 0, 300 poses, geometry only",
                  "residual_head": stored.residual is not None, "stiffness": getattr(stored, "stiffness", None) is not None},
        "targets": {"floor_multiple_median": 4.0, "floor_multiple_p99": 8.0,
                    "monitor_f32_batch_poses_per_s": 1e6},
        "call_floor": latency["one-node graph (call floor)"],
        "call_floor_alone": floor_alone,
        "blocks": blocks,
        "node_floor": {"executed_nodes": n_executed, "chain": chain_name},
        "call_paths": {k: v for k, v in latency.items() if k.startswith(("compensator via", "compensator, "))},
        "parts": parts,
        "graphs": results,
        "convergence": conv,
    }
    atomic_write_json(Path(args.out).with_suffix(".json"), report)
    atomic_write_text(Path(args.out).with_suffix(".md"), markdown(report))
    console.print(markdown(report))
    return 0


def _targets_line(report: dict) -> str:
    """The latency target against this run's one-node floor (the default export, float64, one thread, batch 1)."""
    t, floor = report["targets"], report["call_floor"]
    lines = []
    for label, key in (("InferenceSession.run", None), ("the runner's correct_one", "compensator via CompensatorRuntime.correct_one (bound buffers)"),
                       ("the runner's correct", "compensator via CompensatorRuntime.correct")):
        v = report["graphs"]["compensator"]["ort_single_1thread"] if key is None else report["call_paths"][key]
        m, p = v["median_us"] / floor["median_us"], v["p99_us"] / floor["p99_us"]
        met = m <= t["floor_multiple_median"] and p <= t["floor_multiple_p99"]
        lines.append(f"{label} {v['median_us']:.1f} / {v['p99_us']:.1f} us = {m:.1f}x / {p:.1f}x ({'met' if met else 'missed'})")
    f32 = report["graphs"]["monitor_f32"]["ort_batch_all_threads"]["median_poses_per_s"]
    return (f"Target: the default compensator (float64, one thread, batch 1) at most {t['floor_multiple_median']:.0f}x (median) and "
            f"{t['floor_multiple_p99']:.0f}x (p99) the one-node floor of the same round-robin ({floor['median_us']:.1f} / "
            f"{floor['p99_us']:.1f} us). This run, the benchmark pose: " + "; ".join(lines) + ". "
            f"Batch throughput of the float32 monitor, all threads: {f32:.3g} poses/s (target >= {t['monitor_f32_batch_poses_per_s']:.0e}).")


def _blocks_lines(report: dict) -> list[str]:
    """The warm-block latencies against the floor measured the same way."""
    blocks = report.get("blocks")
    if not blocks:
        return []
    floor = blocks["one-node graph (call floor)"]
    lines = ["", "Measured in warm blocks instead (each call type many times in a row, in turn for several rounds, medians of "
             "the rounds; no other graph runs between two calls of one, as on a controller):", "",
             "| call | median / p99 (us) | x floor (median / p99) |", "| --- | --- | --- |"]
    for name, v in blocks.items():
        lines.append(f"| {name} | {v['median_us']:.1f} / {v['p99_us']:.1f} | {v['median_us'] / floor['median_us']:.1f} / "
                     f"{v['p99_us'] / floor['p99_us']:.1f} |")
    return lines + _node_floor_lines(report)


def node_budget(floor_us: float, chain_us: float, chain_nodes: int, multiple: float) -> tuple[float, float]:
    """``(us per trivial node, most trivial nodes within multiple x floor_us)`` from a one-node call
    (``floor_us``) and a chain of ``chain_nodes`` trivial nodes (``chain_us``), latency linear in nodes."""
    per_node = (chain_us - floor_us) / max(chain_nodes - 1, 1)
    return per_node, 1.0 + (multiple - 1.0) * floor_us / per_node


def _node_floor_lines(report: dict) -> list[str]:
    """The compensator against a chain of as many trivial nodes, and the node count the target allows."""
    node_floor, blocks = report.get("node_floor"), report["blocks"]
    if not node_floor:
        return []
    floor, chain, full = (blocks[k]["median_us"] for k in ("one-node graph (call floor)", node_floor["chain"], "compensator"))
    n = node_floor["executed_nodes"]
    per_node, budget = node_budget(floor, chain, n, report["targets"]["floor_multiple_median"])
    return ["", f"For the benchmark pose onnxruntime runs {n} nodes of the compensator (its profiler's kernel events). "
            f"A chain of {n} trivial nodes (`Sin`, `Neg` on the input) costs {chain:.1f} us: {per_node:.2f} us per node "
            f"beyond the call. The compensator costs {full / chain:.1f}x that chain (its nodes are matrix products, "
            f"splits and reductions on larger tensors). The target of {report['targets']['floor_multiple_median']:.0f}x the "
            f"one-node call ({report['targets']['floor_multiple_median'] * floor:.1f} us) leaves room for at most "
            f"{budget:.0f} trivial nodes in all; one Newton step of the graph alone is "
            f"{min(v for k, v in report['parts']['nodes'].items() if k.startswith('steps_'))}-"
            f"{max(v for k, v in report['parts']['nodes'].items() if k.startswith('steps_'))} nodes."]


def _parts_lines(report: dict) -> list[str]:
    """Nodes per part, the steps poses take, and the latency by part (floor, start + one step + finish, each further step)."""
    parts = report.get("parts")
    if not parts:
        return []
    lines = ["", "## The default compensator by part", "",
             "Nodes after onnxruntime's optimization (`ORT_ENABLE_ALL`); a `Loop` body runs once per step:", "",
             "| part | nodes |", "| --- | --- |"]
    lines += [f"| {k} | {v} |" for k, v in parts["nodes"].items()]
    lines += ["", "Steps taken (phase: {steps: poses}); a pose stops once converged:", "", "| poses | mixed steps | position-only steps |",
              "| --- | --- | --- |"]
    for label, t in parts["steps"].items():
        lines.append(f"| {label} | {t.get('mixed', {})} | {t.get('position', {})} |")
    g, floor = report["graphs"], report["call_floor"]
    one, full = g["compensator_1_step"]["ort_single_1thread"], g["compensator"]["ort_single_1thread"]
    bench = parts["steps"]["the single-pose benchmark pose"]
    n = sum(int(k) * v for phase in bench.values() for k, v in phase.items())
    lines += ["", f"Latency by part, medians of the same round-robin (the benchmark pose takes {n} steps): the call itself (one-node floor) "
              f"{floor['median_us']:.1f} us; start + one step + finish {one['median_us'] - floor['median_us']:.1f} us beyond the floor "
              f"(the graph capped at one step); each further step "
              f"{(full['median_us'] - one['median_us']) / max(n - 1, 1):.1f} us."]
    return lines


def markdown(report: dict) -> str:
    m = report["machine"]
    lines = [
        "# ONNX compensator benchmark",
        "",
        f"Machine: {m['cpu']}, {m['cores']} cores (1-min load average {m['load_average_1min']['before']:.1f} before, "
        f"{m['load_average_1min']['after']:.1f} after: other work shared the cores); onnxruntime {m['onnxruntime']}, torch {m['torch']}. "
        "Latency: one pose per call from Python (`InferenceSession.run`), median and p99. "
        "Throughput: one large batch per call, median of repeats.",
        "",
        f"Model: {report['model']['folder']} (residual head: {'yes' if report['model']['residual_head'] else 'no'}). "
        f"A one-node graph costs {report['call_floor_alone']['median_us']:.1f} / {report['call_floor_alone']['p99_us']:.1f} us "
        f"(median / p99) per call measured alone, {report['call_floor']['median_us']:.1f} / {report['call_floor']['p99_us']:.1f} us "
        "among the other graphs: the floor of any graph called from Python. Single-sample latencies of all graphs "
        "are measured round-robin, so they share the same load, before any multi-threaded work in the process.",
        "",
        "| graph | what | operators | ORT 1 thread median / p99 (us) | torch 1 thread median / p99 (us) | ORT 1 thread (poses/s) | ORT all threads (poses/s) | torch all threads (poses/s) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for key, e in report["graphs"].items():
        o, t = e["ort_single_1thread"], e["torch_single_1thread"]
        lines.append(
            f"| {key} | {e['description']} | {e['operators']} | {o['median_us']:.1f} / {o['p99_us']:.1f} | {t['median_us']:.1f} / {t['p99_us']:.1f} | "
            f"{e['ort_batch_1thread']['median_poses_per_s']:.3g} | {e['ort_batch_all_threads']['median_poses_per_s']:.3g} | "
            f"{e['torch_batch_all_threads']['median_poses_per_s']:.3g} |"
        )
    lines += ["", "The default compensator through other call paths and under each onnxruntime graph optimization level (same round-robin):", "",
              "| call | median / p99 (us) |", "| --- | --- |"]
    for key, v in report.get("call_paths", {}).items():
        lines.append(f"| {key} | {v['median_us']:.1f} / {v['p99_us']:.1f} |")
    lines += [
        "",
        _targets_line(report),
        *_blocks_lines(report),
        *_parts_lines(report),
        "",
        "## Compensator convergence (float64; positions over the solvable poses, position Jacobian sigma_min > 1 mm/rad)",
        "",
        "| task | poses | iterations | solvable | TCP residual median (m) | p99 (m) | max (m) | share below 1 um | rotation p99 (rad) | largest joint move (rad) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in report["convergence"]:
        lines.append(
            f"| {r['task']} | {r['stratum']} | {r['iterations']} | {r['n_solvable']} | {r['position_p50_m']:.1e} | {r['position_p99_m']:.1e} | "
            f"{r['position_max_m']:.1e} | {r['fraction_below_1um']:.4f} | {r['rotation_p99_rad']:.1e} | {r['joint_step_max_rad']:.2f} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
