"""How well exported compensator commands land on a robot whose true kinematics are known.

Used on the digital twin (``torchcal run``): the controller asks for the TCP where the nominal
model puts it, ``T_instrument_base @ p_nom(q_t)`` (the calibrated registration of the instrument
frame), the compensator turns ``q_t`` into ``q_c``, and the true robot goes to ``p_true(q_c)``. The
3-D distance is what compensation leaves, the number an integrator cares about; it is taken for
the torch graph and for the exported float64 and float32 files run by onnxruntime, on the same
poses, so the export's cost is read off directly.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from torchcal.compensate.onnx_checks import ort_feeds, ort_session, unsolved_distance_m
from torchcal.core.metrics import position_metrics


def compensation_on_true_robot(
    stored,
    graphs: dict[str, torch.nn.Module],
    out_dir: str | Path,
    manifest: dict,
    q_target: torch.Tensor,
    true_positions: Callable[[torch.Tensor], torch.Tensor],
    wrench: torch.Tensor | None = None,
) -> dict:
    """TCP error left on the true robot by the torch and the exported compensators.

    Args:
        stored: the :class:`~torchcal.stages.store.StoredModel` that was exported.
        graphs: its torch graphs (:func:`torchcal.compensate.graphs.build_graphs`).
        out_dir: the exported folder (``manifest["files"]`` inside it).
        manifest: the export's manifest.
        q_target: ``(B, N)`` rad, nominal commands (the targets are their nominal TCPs).
        true_positions: ``q (B, N) rad -> (B, 3)`` true TCP positions in the calibration's
            instrument frame, m (for the twin, :meth:`Twin.true_positions`).
        wrench: ``(B, 6)`` expected load for graphs with a stiffness stage, else ``None``.

    Returns:
        ``{"n_poses", "uncompensated", "torch", "onnx_float64", "onnx_float32", "model_own_error"}`` with the
        position metrics (mm) of each (the last: true minus model-predicted TCP at ``q``), and ``onnx_float64_over_torch`` / ``onnx_float32_over_torch``:
        ratios of RMS error (1.0 = the export loses nothing); ``solved_share``, the share of poses
        whose command puts the model's predicted TCP within 1 um of the target, and
        ``torch_on_solved`` / ``torch_on_unsolved``: the torch metrics on either part.
    """
    out_dir = Path(out_dir)
    q = q_target.to(torch.float64)
    T = stored.model.instrument_from_base(stored.x).detach().cpu()
    target = stored.robot.tcp_position(q) @ T[:3, :3].T + T[:3, 3]
    wrench = None if wrench is None else wrench.to(torch.float64)
    args = (q,) if wrench is None else (q, wrench)
    w = None if wrench is None else wrench.numpy()
    with torch.no_grad():
        commands = {"uncompensated": q, "torch": graphs["compensator"](*args)}
    for key, dtype in (("compensator", np.float64), ("compensator_f32", np.float32)):
        session = ort_session(out_dir / manifest["files"][key])
        out = session.run(None, ort_feeds(session, q.numpy().astype(dtype), w))[0]
        commands["onnx_float64" if dtype == np.float64 else "onnx_float32"] = torch.from_numpy(out).to(torch.float64)
    result: dict = {"n_poses": int(q.shape[0])}
    with torch.no_grad():
        errors = {name: true_positions(q_c) - target for name, q_c in commands.items()}
    for name, error in errors.items():
        result[name] = position_metrics(error)
    torch_rms = result["torch"]["position_rms_mm"]
    # the model's own error at this TCP (true minus predicted at the same joints): what no compensator
    # can remove, the yardstick of the compensated error (a TCP away from the measured point sees the
    # orientation the position data determined less well)
    with torch.no_grad():  # the monitor graph: the model's whole prediction (geometry, joint-space terms, head)
        predicted_base = stored.robot.tcp_position(q) + graphs["monitor"](*args)
        result["model_own_error"] = position_metrics(true_positions(q) - (predicted_base @ T[:3, :3].T + T[:3, 3]))
    result["onnx_float64_over_torch"] = result["onnx_float64"]["position_rms_mm"] / torch_rms
    result["onnx_float32_over_torch"] = result["onnx_float32"]["position_rms_mm"] / torch_rms
    # Split the poses by whether the fixed Newton steps solved the model's own equations (the
    # predicted real TCP within 1 um of the target): the rest lie near a singularity, where the
    # damped steps correct only part of the error, and they make the tail of the torch numbers.
    solved = unsolved_distance_m(graphs, stored.robot, q, commands["torch"], wrench) <= 1e-6
    error = errors["torch"]
    result["solved_share"] = float(solved.double().mean())
    result["torch_on_solved"] = position_metrics(error[solved]) if bool(solved.any()) else None
    result["torch_on_unsolved"] = position_metrics(error[~solved]) if bool((~solved).any()) else None
    return result
