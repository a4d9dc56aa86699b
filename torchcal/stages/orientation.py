"""The tool's orientation scored where a file measures it (``rx, ry, rz``): the model's and the nominal robot's.

What is scored is the orientation a compensator acts on (:func:`orientation_source_of`): the
calibrated chain's flange orientation, with its joint-space terms where the fit measured the
orientation and by the geometry alone (the MDH table at the commanded joints) where it measured
positions only (a learned residual head corrects positions only, and a stiffness stage's deflection
under a file's wrench is not turned into a rotation here), in the instrument frame, against the
measured one, as the angle of ``R_predicted^T R_measured`` (deg).

**Protocols.** The instrument frame is the model's (``--register``: re-fitted to the file's
positions, as for the position errors). The probe's rotation on the flange is a constant the fit
identified only if it measured orientation; otherwise it is fitted to the file's orientations first
(3 parameters: the nominal robot gets the same), so that what remains is the orientation error that
varies from pose to pose: what a position-only calibration may claim to know about the orientation.
The nominal robot's instrument frame is the one fitted to the file's positions
(:func:`~torchcal.stages.geometry.nominal_fit`), its probe rotation fitted as above.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.core.errors import DataError
from torchcal.data.measurements import Measurements
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import RobotModel
from torchcal.stages.geometry import model_joints, registered_frame
from torchcal.stages.store import StoredModel

PROBE_FITTED = "probe rotation on the flange fitted to these orientations"
#: Orientation columns the nominal robot misses by more than this (deg RMS, probe rotation fitted) are refused:
#: an arm's geometry turns its tool by tenths of a degree, a wrong angle convention by degrees (near ry = 90 deg,
#: where rx and rz nearly coincide, at some poses only: hence the RMS, not the median).
IMPLAUSIBLE_RMS_DEG = 2.0
PROBE_IDENTIFIED = "probe rotation as the fit identified it from measured orientations"


ORIENTATION_SOURCES = ("model", "geometry")
"""What a compensator orients the tool by: the whole calibrated chain (joint-space errors included),
or its geometry alone (the MDH table at the commanded joints)."""


def orientation_source_of(model: ErrorModel, requested: str | None = None) -> str:
    """``requested``, or by default ``model`` where the calibration measured the tool's orientation and
    ``geometry`` where it measured positions only.

    Joint-space errors fitted to positions alone move the measured point through the lever of the
    joints after them, and may stand for errors that are not rotations of those joints: measured on
    the IRB 120's three SMRs, such terms turn the tool five times further from the truth than the
    nominal robot does, while the calibrated geometry alone stays closer than the nominal robot
    (``scripts/orientation_real.py``, docs/prior.md).
    """
    if requested is None:
        return "model" if model.with_orientation else "geometry"
    if requested not in ORIENTATION_SOURCES:
        raise ValueError(f"orientation_source must be one of {list(ORIENTATION_SOURCES)}, got {requested!r}")
    return requested


def oriented_joints(stored: StoredModel, q: torch.Tensor) -> torch.Tensor:
    """Joints (rad) at which the calibrated chain gives the orientation a compensator acts on: ``q``
    plus the joint-space errors for a ``model`` source, ``q`` itself for ``geometry``."""
    return model_joints(stored, q) if orientation_source_of(stored.model) == "model" else q


@dataclass(frozen=True)
class OrientationErrors:
    """Angles ``(n,)`` (rad) between predicted and measured tool orientations, and how they were obtained."""

    angles_rad: torch.Tensor
    protocol: str

    def metrics(self) -> dict:
        """RMS, mean, p95 and largest angle (deg), the pose count and the protocol."""
        deg = self.angles_rad.detach().cpu().to(torch.float64) * (180.0 / math.pi)
        return {"n_poses": int(deg.numel()), "orientation_rms_deg": float(deg.pow(2).mean().sqrt()),
                "orientation_mean_deg": float(deg.mean()), "orientation_p95_deg": float(deg.quantile(0.95)),
                "orientation_max_deg": float(deg.max()), "protocol": self.protocol}


def angles_to_measured(predicted: torch.Tensor, measured: torch.Tensor, *, fit_probe: bool) -> torch.Tensor:
    """Angles ``(n,)`` rad between ``predicted`` and ``measured`` rotations ``(n, 3, 3)`` (same frame).

    ``fit_probe``: first right-multiply ``predicted`` by the constant rotation that fits the
    measurements best (``measured ~ predicted X``; the chordal least-squares ``X``).
    """
    if fit_probe:
        predicted = predicted @ tf.project_to_so3((predicted.transpose(-1, -2) @ measured).sum(0))
    return tf.rotation_angle(predicted.transpose(-1, -2) @ measured)


def model_orientation_errors(stored: StoredModel, data: Measurements, *, register: bool = False) -> OrientationErrors:
    """The orientation errors of ``stored`` on ``data`` (which must carry ``rx, ry, rz``); see the module docstring."""
    if data.rotation is None:
        raise ValueError("the file has no orientation columns (rx, ry, rz)")
    model, x = stored.model, stored.x
    with torch.no_grad():
        # with register, the frame the position errors are scored in: re-fitted to the file's points
        frame = registered_frame(stored, data) if register else model.instrument_from_base(x)
        flange = model.base_flange_pose(oriented_joints(stored, data.q), x)
        predicted = frame[:3, :3] @ flange[..., :3, :3] @ model.flange_from_tool(x)[:3, :3]
        angles = angles_to_measured(predicted, data.rotation.to(predicted), fit_probe=not model.with_orientation)
    frame_text = "instrument frame re-fitted to the file's positions (--register)" if register else "the model's instrument frame"
    probe = PROBE_IDENTIFIED if model.with_orientation else f"{PROBE_FITTED} (the fit measured positions only)"
    return OrientationErrors(angles, f"{frame_text}; {probe}")


def nominal_orientation_errors(robot: RobotModel, data: Measurements, T_instrument_base: torch.Tensor) -> OrientationErrors:
    """The nominal robot's orientation errors on ``data``, in the instrument frame ``T_instrument_base``
    ``(4, 4)`` fitted to the file's positions (:func:`~torchcal.stages.geometry.nominal_fit`)."""
    if data.rotation is None:
        raise ValueError("the file has no orientation columns (rx, ry, rz)")
    model = ErrorModel(robot)
    with torch.no_grad():
        flange = model.base_flange_pose(data.q.to(torch.float64), model.nominal_vector())
        predicted = T_instrument_base.to(flange)[:3, :3] @ flange[..., :3, :3]
        angles = angles_to_measured(predicted, data.rotation.to(predicted), fit_probe=True)
    return OrientationErrors(angles, f"nominal robot, instrument frame fitted to these positions; {PROBE_FITTED}")


def refuse_implausible(nominal: OrientationErrors, data: Measurements) -> None:
    """Refuse orientation columns that even the nominal robot (probe rotation fitted) misses by degrees (RMS).

    Raises:
        DataError: naming the RMS angle and the likely cause (the angle convention or unit).
    """
    rms = math.degrees(float(nominal.angles_rad.pow(2).mean().sqrt()))
    if rms > IMPLAUSIBLE_RMS_DEG:
        raise DataError(f"the orientation columns rx, ry, rz disagree with the robot by {rms:.2f} deg (RMS, the "
                        f"nominal robot with the probe rotation fitted; a real arm: tenths of a degree): check their "
                        "convention (fixed-axis XYZ in deg, R = Rz(rz) Ry(ry) Rx(rx), tool in the instrument frame) or "
                        "remove the columns to score positions only", path=data.source)
