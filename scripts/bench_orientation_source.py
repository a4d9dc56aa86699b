"""What orienting the tool by the geometry costs: latency, and orientation on a twin whose joint errors are rotations.

``python scripts/bench_orientation_source.py [--rounds 7] [--calls 3000]``: a twin with gravity sag and
gear errors (true rotations of its joints), fitted to 300 positions with gravity compliance (wrist)
and first harmonics, exported both ways: oriented by the whole chain (``model``) and by the MDH
table alone (``geometry``, the default for a position-only fit). Latency: one pose per call from
Python, one onnxruntime thread, the two graphs in turn for ``rounds`` rounds of ``calls`` warm calls
(median of the rounds' medians). Orientation: the twin's true flange under each graph's commands at
600 poses outside the singular strata, against the nominal target (instrument frame re-fitted to
the poses' positions, the probe rotation fitted), with :func:`torchcal.compensate.replay.errors_of_true_poses`.
Writes ``<out>.json`` and ``<out>.md``.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from torchcal.compensate.compensator import CompensatorGraph, CompensatorWithResidual
from torchcal.compensate.export_checks import regular_mask
from torchcal.compensate.graphs import onnx_bytes
from torchcal.compensate.production_tcp import production_view, tcp_transform
from torchcal.compensate.replay import errors_of_true_poses
from torchcal.config.schema import FitConfig
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.data.measurements import Measurements
from torchcal.kinematics import transforms as tf
from torchcal.sim.twin import Twin, TwinConfig
from torchcal.stages.geometry import fit, save_fit
from torchcal.stages.store import load_model

SOURCES = ("model", "geometry")
PROBE = tf.so3_exp(torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--calls", type=int, default=3000)
    parser.add_argument("--out", default="docs/bench_orientation_source")
    args = parser.parse_args()
    twin = Twin.create(TwinConfig(seed=5, gravity=True, gear=True))
    train = twin.sample(300, torch.Generator().manual_seed(6))
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = fit(twin.robot, train, FitConfig(residual="none", progress=False, gravity_compliance="wrist",
                                                  joint_harmonics="first"))
        stored = production_view(load_model(save_fit(Path(tmp) / "m", twin.robot, train, result, {})),
                                 tcp_transform(None, None))
    graphs = {s: CompensatorGraph.from_stored(stored, orientation_source=s) for s in SOURCES}
    rows = {s: {"latency_us": [], **_orientation(twin, stored, graphs[s])} for s in SOURCES}
    rows["uncompensated"] = _orientation(twin, stored, None)
    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    sessions = {s: ort.InferenceSession(onnx_bytes(CompensatorWithResidual(g), stored.robot.dof, torch.float64, "q_nominal",
                                                   "q_corrected", extra_outputs=("residual",)),
                                        options, providers=["CPUExecutionProvider"]) for s, g in graphs.items()}
    q = stored.robot.sample_joints(200, torch.Generator().manual_seed(1)).numpy()
    for _ in range(args.rounds):
        for s, session in sessions.items():
            rows[s]["latency_us"].append(_median_call_us(session, q, args.calls))
    for s in SOURCES:
        rows[s]["latency_median_us"] = float(np.median(rows[s]["latency_us"]))
        print(f"{s}: {rows[s]['latency_median_us']:.1f} us per call; orientation RMS {rows[s]['orientation_rms_deg']:.4f} deg",
              flush=True)
    out = Path(args.out)
    atomic_write_json(out.with_suffix(".json"), {"rows": rows, "rounds": args.rounds, "calls": args.calls})
    atomic_write_text(out.with_suffix(".md"), _table(rows, args))


def _orientation(twin: Twin, stored, graph: CompensatorGraph | None) -> dict:
    """The twin's true flange under ``graph``'s commands (``None``: the nominal ones), against the target."""
    q = twin.robot.sample_joints(1000, torch.Generator().manual_seed(9), margin=math.radians(5))
    q = q[regular_mask(twin.robot, q)][:600]

    def measured(joints: torch.Tensor) -> Measurements:
        flange = twin.T_instrument_base() @ twin.model.base_flange_pose(joints + twin.joint_deviation(joints), twin.x_true)
        return Measurements(q=joints, position=flange[:, :3, 3], rotation=flange[:, :3, :3] @ PROBE)

    data = measured(q)
    with torch.no_grad():
        q_c = q if graph is None else graph.solve(q)[0]
    truth = measured(q_c)
    metrics = errors_of_true_poses(stored, data, q_c, truth.rotation, truth.position).metrics()
    return {"n_poses": len(q), "orientation_rms_deg": metrics["orientation_rms_deg"], "position_rms_mm": metrics["position_rms_mm"]}


def _median_call_us(session: ort.InferenceSession, q: np.ndarray, calls: int) -> float:
    name = session.get_inputs()[0].name
    for i in range(200):
        session.run(None, {name: q[i % len(q): i % len(q) + 1]})
    times = np.empty(calls)
    for i in range(calls):
        x = q[i % len(q): i % len(q) + 1]
        start = time.perf_counter_ns()
        session.run(None, {name: x})
        times[i] = time.perf_counter_ns() - start
    return float(np.median(times)) / 1e3


def _table(rows: dict, args) -> str:
    lines = ["# Orienting the tool by the geometry: latency and a twin's orientation", "",
             f"Written by `python scripts/bench_orientation_source.py --rounds {args.rounds} --calls {args.calls}`. A twin with "
             "gravity sag and gear errors (true joint rotations), fitted to 300 positions with wrist gravity compliance and "
             "first harmonics; the flange as TCP. Latency: one pose per call, one onnxruntime thread, median of the rounds' "
             "medians. Orientation and position: the twin's true flange under the commands at 600 regular poses, against "
             "the nominal target (frame re-fitted to the positions, probe rotation fitted).", "",
             "| commands | latency median [us] | orientation RMS [deg] | flange position RMS [mm] |", "|---|---|---|---|"]
    for name, r in rows.items():
        latency = f"{r['latency_median_us']:.1f}" if "latency_median_us" in r else "-"
        lines.append(f"| {name} | {latency} | {r['orientation_rms_deg']:.4f} | {r['position_rms_mm']:.4f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
