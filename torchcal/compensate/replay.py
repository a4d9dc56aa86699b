"""What a compensator's commands leave on the real robot, replayed from measured poses.

A measured pose (the measured point's position and, where measured, the tool's orientation at the
commanded joints ``q``) says what the robot does at ``q``, not at a compensator's command
``q_c = q + dq``. To first order in ``dq`` the robot moves between the two as the calibrated model
does: the truth at ``q_c`` is the measured pose moved by the model's own motion of the flange from
``q`` to ``q_c``. What is neglected is the difference between the robot's and the model's motion over
``dq`` (the calibration's remaining error times ``dq``: about 1e-5 rad and 0.01 mm for a 0.5 deg
correction of a 1 m arm whose model is 1e-3 off; `tests/compensate/test_replay.py` checks it against
a twin's truth at the command).

**Target and frames.** The commands serve the measured point as their production TCP (``export
--tcp-mm`` at the model's fitted tool point, :func:`~torchcal.compensate.production_tcp.production_view`):
each aims at where the nominal robot puts that point and the flange's orientation at ``q``, in the
model's robot base frame, which the file's positions locate in the instrument frame (``--register``:
the frame re-fitted to them, as :func:`~torchcal.stages.geometry.held_out_errors` does). The probe's (or nest's) rotation on the
flange is fitted to each command set's orientations (3 parameters, chordal least squares, as
:mod:`torchcal.stages.orientation` does): a position-only fit does not know it, and a user defines a
tool's orientation once, for whichever commands the controller runs.

**Command sets** (:func:`command_sets`): ``uncompensated`` (``q``), ``compensator`` (the default
export's commands), ``position only`` (the same graph with its orientation task damped away: the
position is corrected with the smallest joint motion, and the tool turns however that motion turns
it), and ``capped at C deg`` (the compensator's corrections scaled per pose so that none exceeds ``C``).
:func:`solved_mask` marks the poses whose orientation the compensator reaches in its steps (near the
wrist singularity its bounded wrist swing leaves some short of it): :func:`confirmed_share` judges
the model's orientation change there, not the graph's step budget.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.compensate.compensator import CompensatorGraph
from torchcal.compensate.production_tcp import production_view, tcp_transform
from torchcal.data.measurements import Measurements
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.stages.geometry import model_joints, registered_frame
from torchcal.stages.store import StoredModel

#: Floor of the orientation task's damping (rad/rad) that leaves a ``position only`` graph's orientation steps
#: a millionth of the compensator's: the position is solved, the orientation not touched.
POSITION_ONLY_ORIENTATION_DAMPING = 1e6

PROTOCOL = ("first-order replay of the measured poses: the robot at a command q + dq is the measured pose at q "
            "moved by the model's own flange motion over dq; TCP: the measured point (the model's fitted tool point); "
            "target: where the nominal robot puts it and the flange's orientation at q, in the model's base frame "
            "re-fitted to the file's positions; probe rotation on the flange fitted to each command set's orientations")


@dataclass(frozen=True)
class Replayed:
    """What one command set leaves at the measured poses.

    ``rotation_error``: ``(n, 3)`` rad, the rotation vector from the target orientation to the
    replayed one, in the tool frame (``None`` where the file measures no orientation).
    ``position_error``: ``(n, 3)`` m, replayed minus target position of the measured point.
    ``largest_correction``: ``(n,)`` rad, the command's largest joint correction per pose.
    """

    rotation_error: torch.Tensor | None
    position_error: torch.Tensor
    largest_correction: torch.Tensor

    def metrics(self) -> dict:
        """RMS orientation (deg, ``None`` without orientation) and position (mm), joint corrections (deg)."""
        if not len(self.position_error):
            raise ValueError("no poses replayed")
        out: dict[str, float | None] = {"position_rms_mm": float(self.position_error.norm(dim=-1).pow(2).mean().sqrt()) * 1e3,
               "largest_joint_correction_deg": math.degrees(float(self.largest_correction.max())),
               "median_joint_correction_deg": math.degrees(float(self.largest_correction.median()))}
        angles = None if self.rotation_error is None else self.rotation_error.norm(dim=-1)
        out["orientation_rms_deg"] = None if angles is None else math.degrees(float(angles.pow(2).mean().sqrt()))
        return out


def solved_mask(stored: StoredModel, q: torch.Tensor, tolerance_rad: float = 1e-6) -> torch.Tensor:
    """``(n,)`` bool: the poses of ``q`` whose orientation :func:`command_sets`' compensator reaches within
    ``tolerance_rad`` (its ``residual`` output), the position being solved everywhere but at a singularity."""
    with torch.no_grad():
        _, residual = CompensatorGraph.from_stored(production_view(stored, measured_point(stored))).solve(q.to(torch.float64))
    return residual[:, 1] < tolerance_rad


def command_sets(stored: StoredModel, q: torch.Tensor, cap_deg: float = 0.3) -> dict[str, torch.Tensor]:
    """Commands ``(n, N)`` rad for the joints ``q`` of each command set of the module docstring."""
    view = production_view(stored, measured_point(stored))
    q = q.to(torch.float64)
    with torch.no_grad():
        full = CompensatorGraph.from_stored(view).solve(q)[0]
        position_only = CompensatorGraph.from_stored(
            view, orientation_damping=POSITION_ONLY_ORIENTATION_DAMPING).solve(q)[0]
    correction = full - q
    largest = correction.abs().amax(-1, keepdim=True)
    scale = (math.radians(cap_deg) / largest.clamp_min(1e-300)).clamp(max=1.0)
    return {"uncompensated": q, "compensator": full, "position only": position_only,
            f"capped at {cap_deg:g} deg": q + scale * correction}


def measured_point(stored: StoredModel) -> torch.Tensor:
    """``T_flange_tcp`` ``(4, 4)`` of the model's fitted tool point (no rotation: the commands keep the flange's)."""
    return tcp_transform([float(v) * 1e3 for v in stored.x[stored.model.layout.tool_slice][:3]], None)


def replay(stored: StoredModel, data: Measurements, commands: dict[str, torch.Tensor]) -> dict[str, Replayed]:
    """Each command set of ``commands`` (for ``data.q``) replayed at ``data``'s measured poses (module docstring)."""
    model, x = stored.model, stored.x
    q = data.q.to(torch.float64)
    with torch.no_grad():
        frame = registered_frame(stored, data)
        at_q = frame @ model.base_flange_pose(model_joints(stored, q), x)
        tool = model.flange_from_tool(x)
        point_at_q = (at_q @ tool)[:, :3, 3]
        probe = None
        if data.rotation is not None:  # the probe's rotation on the model's flange: the measured rotation's relative motion
            probe = tf.project_to_so3((at_q[:, :3, :3].transpose(-1, -2) @ data.rotation).sum(0))
        out = {}
        for name, q_c in commands.items():
            at_c = frame @ model.base_flange_pose(model_joints(stored, q_c.to(torch.float64)), x)
            position = data.position + (at_c @ tool)[:, :3, 3] - point_at_q
            rotation = None
            if probe is not None and data.rotation is not None:
                motion = at_q[:, :3, :3].transpose(-1, -2) @ at_c[:, :3, :3]  # flange frame
                rotation = data.rotation @ probe.T @ motion @ probe
            out[name] = _against_target(stored, data, q, frame, rotation, position, (q_c - q).abs().amax(-1))
    return out


def _against_target(stored: StoredModel, data: Measurements, q: torch.Tensor, frame: torch.Tensor,
                    rotation: torch.Tensor | None, position: torch.Tensor, largest: torch.Tensor) -> Replayed:
    """Errors of poses reached at ``data``'s targets: ``rotation`` ``(n, 3, 3)`` (or ``None``) and the measured
    point's ``position`` ``(n, 3)`` m, both in the instrument frame (the module docstring's target and frames)."""
    nominal = ErrorModel(stored.robot)
    target = frame @ nominal.base_flange_pose(q, nominal.nominal_vector())
    tool = stored.model.flange_from_tool(stored.x)
    position_error = position - (target @ tool)[:, :3, 3]
    rotation_error = None
    if rotation is not None:
        wanted = target[:, :3, :3]
        wanted = wanted @ tf.project_to_so3((wanted.transpose(-1, -2) @ rotation).sum(0))
        rotation_error = tf.so3_log(wanted.transpose(-1, -2) @ rotation)
    return Replayed(rotation_error, position_error, largest)


def errors_of_true_poses(stored: StoredModel, data: Measurements, q_c: torch.Tensor, rotation: torch.Tensor | None,
                         position: torch.Tensor) -> Replayed:
    """The errors of poses measured *at* the commands ``q_c`` (a twin's truth there), against ``data``'s targets
    with the same frame and probe fit as :func:`replay`: the independent check of the replay."""
    q = data.q.to(torch.float64)
    with torch.no_grad():
        return _against_target(stored, data, q, registered_frame(stored, data), rotation, position, (q_c - q).abs().amax(-1))


def confirmed_share(uncompensated: Replayed, compensated: Replayed) -> float:
    """How much of the orientation change the compensator makes the measured orientations confirm.

    The least-squares multiple ``c`` of the change ``d = r_0 - r_1`` (rotation vectors before and
    after) that best explains the error before, ``r_0``: ``c = <r_0, d> / <d, d>``. 1: the change is
    what the robot needed; 0: it is unrelated to the robot's error; below 0: it makes the error worse.
    """
    if uncompensated.rotation_error is None or compensated.rotation_error is None:
        raise ValueError("the file measures no orientation")
    change = uncompensated.rotation_error - compensated.rotation_error
    size = float((change * change).sum())
    if size == 0.0:
        raise ValueError("the commands do not turn the tool: there is no change to confirm")
    return float((uncompensated.rotation_error * change).sum()) / size
