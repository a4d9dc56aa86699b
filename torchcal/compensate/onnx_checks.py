"""What the export checks share: an onnxruntime session, its inputs, and what a command left unsolved."""

from __future__ import annotations

from pathlib import Path

import torch


def ort_session(path: Path):
    """A quiet CPU onnxruntime session of the file at ``path``: on one thread in a worker process (a
    check run there beside the main process's work takes no core from it), else on onnxruntime's
    default; per-pose graphs give the same numbers on any count."""
    import onnxruntime as ort

    from torchcal.core.workers import in_worker

    options = ort.SessionOptions()
    options.log_severity_level = 3
    if in_worker():
        options.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def ort_feeds(session, q, wrench=None) -> dict:
    """Input dict of an ORT session: joints first, then the wrench where the graph takes one."""
    names = [i.name for i in session.get_inputs()]
    feeds = {names[0]: q}
    if len(names) > 1:
        feeds[names[1]] = wrench.astype(q.dtype)
    return feeds


def unsolved_distance_m(graphs: dict[str, torch.nn.Module], robot, q_target: torch.Tensor, q_command: torch.Tensor,
                        wrench: torch.Tensor | None = None) -> torch.Tensor:
    """``|p_nom(q_c) + monitor(q_c) - p_nom(q_t)|`` ``(B,)``, m: how far the model's predicted real
    TCP at the command ``q_c`` lies from the nominal target of ``q_t`` (what the fixed number of
    Newton steps left unsolved; ``wrench`` for graphs with a stiffness stage)."""
    extra = () if wrench is None else (wrench,)
    with torch.no_grad():
        landed = robot.tcp_position(q_command) + graphs["monitor"](q_command, *extra)
    return (landed - robot.tcp_position(q_target)).norm(dim=-1)
