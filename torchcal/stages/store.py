"""Saving and loading a calibrated model folder (no pickles anywhere).

A model folder holds:

* ``robot.yaml`` or ``robot.urdf``: the nominal robot it was calibrated from;
* ``calibration.safetensors``: tensors ``x`` (full parameter vector, SI), ``T_reference``
  (instrument-from-base, 4x4), ``free`` (estimated parameter indices), ``covariance`` and,
  for fits from measured poses, ``training_q`` (their commanded joints, rad);
* ``calibration.json``: metadata (parameter names, units, identifiability, data hash, metrics)
  and ``frames``: the instrument-to-base transform and the tool, mm and deg with 1-sigma (the
  ``base_*`` and ``tool_*`` parameters hold the same values; see :data:`FRAME_CONVENTION`);
* ``calibrated_robot.yaml``: the calibrated MDH table in the contract's units, for people, with a
  header saying what of the model it leaves out;
* ``calibrated_robot.urdf``: the robot's own URDF (or one generated from the MDH table) with the
  calibrated joint origins and the TCP as an added link (:mod:`torchcal.kinematics.calibrated_urdf`);
* optionally ``report.md`` + ``report.html`` (figures in ``figures/``): the calibration report;
* optionally ``residual.safetensors`` + ``residual.json``: a learned residual head;
* optionally ``model_selection.json``: the cross-validated comparison the fit chose by;
* optionally ``stiffness.safetensors`` + ``stiffness.json``: joint stiffness
  (:mod:`torchcal.stages.stiffness_store`).
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import torch

from torchcal.core.errors import ModelError
from torchcal.core.folder import verify_folder, write_member, write_member_json, write_member_text
from torchcal.core.hashing import sha256_bytes, sha256_file
from torchcal.identify.joint_errors import JointSpaceErrors
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.calibrated_urdf import calibrated_urdf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import RobotModel, load_robot, robot_to_yaml
from torchcal.kinematics.transforms import matrix_to_euler_xyz
from torchcal.stages.base import (
    GeometryStage,
    JointErrorStage,
    ResidualStage,
    StiffnessStage,
)
from torchcal.stages.files import read_json_member, read_tensors
from torchcal.stages.residual_store import load_residual
from torchcal.stages.stiffness_store import load_stiffness_stage

if TYPE_CHECKING:  # annotations only
    from torchcal.stages.base import ModelStage
    from torchcal.stages.residual_store import StoredResidual
    from torchcal.stages.stiffness_store import StoredStiffness


@dataclass
class StoredModel:
    """A calibrated model as loaded from disk."""

    robot: RobotModel
    model: ErrorModel
    x: torch.Tensor
    free: torch.Tensor
    covariance: torch.Tensor
    metadata: dict
    folder: Path
    extras: dict = field(default_factory=dict)
    training_q: torch.Tensor | None = None
    parts: dict[str, object] = field(default_factory=dict)
    """The stages read from files of their own (:data:`OPTIONAL_STAGES`), by stage name."""
    joint_covariance: torch.Tensor | None = None
    """Where joint-space terms were identified with the geometry: the covariance of ``free`` and then
    of their coefficients ``joint_coefficients`` ``(K, 2)`` (row, joint); else ``None``."""
    joint_coefficients: torch.Tensor | None = None

    @property
    def free_names(self) -> list[str]:
        return [self.model.layout.names[i] for i in self.free.tolist()]

    def stages(self) -> list[ModelStage]:
        """The model's stages in the order a prediction applies them (absent ones left out).

        Built on each call from the folder's parts and the current ``model`` and ``x`` (a
        production-TCP view replaces those), so no stage holds a stale chain."""
        out: list[ModelStage] = []
        errors = JointSpaceErrors.from_metadata(self.metadata)
        if not errors.empty:
            out.append(JointErrorStage(errors))
        out.append(GeometryStage(self.model, self.x))
        for name, optional in OPTIONAL_STAGES.items():
            if name in self.parts:
                out.append(optional.stage(self.parts[name], self))
        return out

    @property
    def residual(self) -> StoredResidual | None:
        """The learned residual head, or ``None`` (the ``residual`` part)."""
        return cast("StoredResidual | None", self.parts.get("residual"))

    @residual.setter
    def residual(self, value: StoredResidual | None) -> None:
        self._set_part("residual", value)

    @property
    def stiffness(self) -> StoredStiffness | None:
        """The joint stiffness, or ``None`` (the ``stiffness`` part)."""
        return cast("StoredStiffness | None", self.parts.get("stiffness"))

    @stiffness.setter
    def stiffness(self, value: StoredStiffness | None) -> None:
        self._set_part("stiffness", value)

    def _set_part(self, name: str, value: object | None) -> None:
        # a new dict, not an edit: a view made by dataclasses.replace (a production TCP) shares ``parts``
        parts = {k: v for k, v in self.parts.items() if k != name}
        if value is not None:
            parts[name] = value
        self.parts = parts


@dataclass(frozen=True)
class OptionalStage:
    """A stage a model folder holds in files of its own: how to read its part and make the stage.

    Attributes:
        load: ``(folder, device) -> part`` or ``None`` where the folder has none; raises
            :class:`ModelError` naming the file when it cannot be read.
        stage: ``(part, stored) -> ModelStage`` bound to the stored model's current chain.
    """

    load: Callable[[Path, str | torch.device], object | None]
    stage: Callable[[Any, StoredModel], ModelStage]


def _load_residual_part(folder: Path, device: str | torch.device) -> StoredResidual | None:
    has_json, has_tensors = (folder / "residual.json").is_file(), (folder / "residual.safetensors").is_file()
    if has_json != has_tensors:  # half a head: never scored as a model without one
        present, absent = ("residual.json", "residual.safetensors") if has_json else ("residual.safetensors", "residual.json")
        raise ModelError(f"{folder / present}: the residual head's {absent} is missing; the folder is incomplete")
    if not has_json:
        return None
    try:
        return load_residual(folder)
    except (KeyError, TypeError, ValueError, AssertionError, RuntimeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ModelError(f"{folder / 'residual.json'}: the residual head cannot be read ({first})") from None


def _residual_stage(part: StoredResidual, stored) -> ResidualStage:
    if part.features.mid.shape[0] != stored.robot.dof:
        raise ModelError(f"the residual head takes {part.features.mid.shape[0]} joints, the model's robot "
                         f"{stored.robot.name} has {stored.robot.dof}")
    return ResidualStage(part, stored.model.T_reference[:3, :3])


#: The optional stages in the order a prediction applies them: adding one is a module with its
#: part's loader and stage class plus one line here.
OPTIONAL_STAGES: dict[str, OptionalStage] = {
    "residual": OptionalStage(_load_residual_part, _residual_stage),
    "stiffness": OptionalStage(lambda folder, device: load_stiffness_stage(folder, device=device),
                               lambda part, stored: StiffnessStage(part, stored.model, stored.x)),
}


def save_model(
    folder: str | Path,
    robot: RobotModel,
    model: ErrorModel,
    x: torch.Tensor,
    free: torch.Tensor,
    cov: torch.Tensor,
    metadata: dict,
    training_q: torch.Tensor | None = None,
    joint_covariance: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> Path:
    """Write a model folder; every file is written atomically.

    ``training_q`` ``(n, N)`` rad: the commanded joints of the poses fitted, kept so that
    ``evaluate`` can say how close scored poses sit to them
    (:mod:`torchcal.model_selection.leakage`). ``joint_covariance``: where joint-space terms were
    identified with the geometry, the joint covariance and the coefficients it covers after ``free``
    (:attr:`~torchcal.identify.calibrate.CalibrationResult.joint_covariance`).
    """
    from safetensors.torch import save

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if robot.source and Path(robot.source).suffix.lower() in (".urdf", ".xml"):
        robot_file = folder / "robot.urdf"
        robot_text = robot.urdf or Path(robot.source).read_text()
    else:
        robot_file = folder / "robot.yaml"
        robot_text = robot_to_yaml(robot)
    write_member_text(folder, robot_file.name, robot_text)
    tensors = {
        "x": x.detach().cpu().contiguous(),
        "T_reference": model.T_reference.detach().cpu().contiguous(),
        "free": free.detach().cpu().contiguous(),
        "covariance": cov.detach().cpu().contiguous(),
    }
    if training_q is not None:
        tensors["training_q"] = training_q.detach().to("cpu", torch.float64).contiguous()
    if joint_covariance is not None:
        tensors["joint_covariance"] = joint_covariance[0].detach().to("cpu", torch.float64).contiguous()
        tensors["joint_coefficients"] = joint_covariance[1].detach().to("cpu", torch.long).contiguous()
    write_member(folder, "calibration.safetensors", save(tensors))
    scale = model.layout.unit_scale()
    sigma = torch.zeros(model.layout.size, dtype=torch.float64)
    sigma[free] = cov.diagonal().clamp_min(0).sqrt().cpu()
    estimated = set(free.tolist())
    parameters = {
        n: {"value": float(v * s), "sigma": float(sg * s), "estimated": i in estimated}
        for i, (n, v, s, sg) in enumerate(zip(model.layout.names, x.cpu().tolist(), scale.tolist(), sigma.tolist()))
    }
    frames = frame_entries(model, x, free, cov)
    for key, transform in (("base", "T_instrument_base"), ("tool", "T_flange_tool")):
        for axis in ("x", "y", "z", "rx", "ry", "rz"):
            parameters[f"{key}_{axis}"].update(value=frames[transform][axis], sigma=frames[transform]["sigma"][axis])
    meta = {
        "format": "torchcal-model/1",
        "robot_file": robot_file.name,
        "robot_sha256": sha256_bytes(robot_text.encode("utf-8")),
        "robot_name": robot.name,
        "base_link": robot.base_link,
        "end_link": robot.end_link,
        "nominal_tool_mm": (robot.tool.detach().cpu() * 1e3).tolist(),
        "parallel_threshold_deg": model.parallel_threshold_deg,
        "with_orientation": model.with_orientation,
        "parameter_names": list(model.layout.names),
        "units": {"lengths": "mm", "angles": "deg"},
        "parameters": parameters,
        "frames": frames,
        **metadata,
    }
    write_member_json(folder, "calibration.json", meta)
    # the contract's table ends in MDH frame N and its tool point is taken there: a fixed frame N -> flange
    # (a URDF's) is folded into the point, exact for the TCP's position (it was dropped: 0.38 mm off)
    tool = robot.T_n_flange.to(torch.float64)[:3, :3] @ x[model.layout.tool_slice][:3].cpu().to(torch.float64) \
        + robot.T_n_flange.to(torch.float64)[:3, 3]
    write_member_text(folder, "calibrated_robot.yaml",
                      calibrated_yaml_header(robot, meta) + robot_to_yaml(robot, table=model.table(x.cpu()), tool=tool))
    urdf, _ = calibrated_urdf(robot, model.table(x.cpu()), model.flange_from_tool(x.cpu()).cpu(), urdf_notes(robot, meta))
    write_member_text(folder, CALIBRATED_URDF, urdf)
    return folder


#: The calibrated URDF of a model folder (:mod:`torchcal.kinematics.calibrated_urdf`).
CALIBRATED_URDF = "calibrated_robot.urdf"


def not_in_geometry(meta: dict) -> list[str]:
    """What of a model a geometry file (calibrated YAML or URDF) cannot hold, one line each."""
    lines = []
    terms = [name for key, name in (("gravity_compliance", "gravity compliance"), ("joint_harmonics", "periodic joint errors"))
             if meta.get(key)]
    if terms:
        lines.append(f"Not in this file: {' and '.join(terms)} (calibration.json), joint-space errors added to the commanded "
                     "joints before this geometry; without them this file is not the model that was fitted.")
    lines.append("Not in this file either: a learned residual head (residual.safetensors) or joint stiffness "
                 "(stiffness.safetensors), where the folder has them.")
    return lines


def urdf_notes(robot: RobotModel, meta: dict) -> list[str]:
    """The comment of ``calibrated_robot.urdf``: what changed and what the file cannot hold."""
    data = meta.get("data") or {}
    source = f" from {Path(str(data['file'])).name} ({data.get('n_poses')} poses)" if data.get("file") else ""
    origin = "this robot's URDF" if robot.urdf is not None else "a URDF generated from the calibrated MDH table"
    lines = [f"Calibrated by torchcal{source}: {origin} with only the origins of the moving joints changed",
             "(joint zero offsets folded in). Links, visuals, collisions, inertials, limits and axes are as given.",
             f"The calibrated tool point (TCP) is the origin of the added link '{robot.end_link}_calibrated_tcp'.",
             "The instrument-to-base transform of the measurement is in calibration.json (frames), not here."]
    return lines + not_in_geometry(meta)


#: How ``calibration.json`` ``frames`` (and the ``base_*`` / ``tool_*`` parameters) write a transform.
FRAME_CONVENTION = ("T_a_b is the pose of frame b in frame a: x, y, z its translation (mm), rx, ry, rz its rotation as "
                    "fixed-axis XYZ angles (deg, R = Rz(rz) Ry(ry) Rx(rx), the convention of the measurement files' "
                    "rx, ry, rz); sigma: 1-sigma from the fit's covariance (0 where not estimated)")


def _transform_readout(transform_of, b: torch.Tensor, cov: torch.Tensor) -> dict:
    """``x..rz`` (mm, deg) of ``transform_of(b)`` and their 1-sigma, ``cov`` the covariance of ``b`` (SI)."""
    def readout(v: torch.Tensor) -> torch.Tensor:
        t = transform_of(v)
        return torch.cat([t[:3, 3] * 1e3, torch.rad2deg(matrix_to_euler_xyz(t[:3, :3]))])

    b = b.detach().cpu().to(torch.float64)
    values = readout(b)
    jac = torch.autograd.functional.jacobian(readout, b)
    sigma = (jac @ cov @ jac.T).diagonal().clamp_min(0).sqrt()
    transform = transform_of(b)
    matrix = torch.cat([torch.cat([transform[:3, :3], transform[:3, 3:] * 1e3], 1), transform[3:]], 0)
    axes = ("x", "y", "z", "rx", "ry", "rz")
    return {**{a: float(v) + 0.0 for a, v in zip(axes, values.tolist())},  # + 0.0: no -0.0 in the file
            "sigma": {a: float(v) for a, v in zip(axes, sigma.tolist())},
            "matrix_mm": [[float(v) for v in row] for row in matrix.tolist()]}


def frame_entries(model: ErrorModel, x: torch.Tensor, free: torch.Tensor, cov: torch.Tensor) -> dict:
    """``T_instrument_base`` and ``T_flange_tool`` of a fit, in mm and deg with 1-sigma (``calibration.json`` ``frames``).

    ``x`` holds the base *correction* on the right of ``model.T_reference`` (so its ``base_*``
    entries are near zero); the transform written here is the whole one, the sigmas propagated
    from the covariance ``cov`` ``(K, K)`` of the parameters ``free`` ``(K,)``.
    """
    layout = model.layout
    full = torch.zeros(layout.size, layout.size, dtype=torch.float64)
    index = free.detach().cpu().long()
    full[index.unsqueeze(1), index.unsqueeze(0)] = cov.detach().cpu().to(torch.float64)
    reference = model.T_reference.detach().cpu().to(torch.float64)
    base, tool = layout.base_slice, layout.tool_slice

    def instrument_from_base(b: torch.Tensor) -> torch.Tensor:
        return reference @ tf.homogeneous(tf.so3_exp(b[3:]), b[:3])

    def flange_from_tool(b: torch.Tensor) -> torch.Tensor:
        return tf.homogeneous(tf.so3_exp(b[3:]), b[:3])

    x = x.detach().cpu().to(torch.float64)
    return {
        "convention": FRAME_CONVENTION,
        "T_instrument_base": _transform_readout(instrument_from_base, x[base], full[base, base]),
        "T_flange_tool": _transform_readout(flange_from_tool, x[tool], full[tool, tool]),
    }


def calibrated_yaml_header(robot: RobotModel, meta: dict) -> str:
    """The comment block of ``calibrated_robot.yaml``: what the table is, and what of the model it leaves out."""
    data = meta.get("data") or {}
    source = f" from {Path(str(data['file'])).name} ({data.get('n_poses')} poses)" if data.get("file") else ""
    lines = [(f"calibrated by torchcal{source}: the geometric stage only, the identified MDH table and tool point "
             "(mm, deg). The instrument-to-base transform and every parameter's 1-sigma are in calibration.json "
             "(frames, parameters).")]
    lines += not_in_geometry(meta)
    dropped = list((meta.get("identifiability") or {}).get("not_identifiable") or {})
    if dropped:
        lines.append(f"Not identified from the data, so at their nominal values: {', '.join(dropped)}.")
    eye = torch.eye(4, dtype=torch.float64)
    if not torch.allclose(robot.T_n_flange, eye):
        lines.append(f"The table runs from MDH frame 0 to frame N; the fixed transform frame N -> flange of "
                     f"{meta.get('robot_file', 'the robot file')} has no field in this format: it is folded into the "
                     "tool point, which is therefore given in frame N (the TCP's position is exact; the flange's "
                     "orientation is not represented).")
    if not torch.allclose(robot.T_base_0, eye):
        lines.append(f"The fixed transform base -> frame 0 of {meta.get('robot_file', 'the robot file')} has no field "
                     "in this format and is not in it: positions of this table are in MDH frame 0, not the base frame.")
    import textwrap

    wrapped = [w for line in lines for w in textwrap.wrap(line, 100)]
    return "".join(f"# {w}\n" for w in wrapped)


def _member_path(folder: Path, name: object, key: str) -> Path:
    """``folder/name`` for a file name stored in ``calibration.json``; a path leading outside is refused."""
    if not isinstance(name, str) or not name or Path(name).name != name or name in (".", ".."):
        raise ModelError(f"{folder / 'calibration.json'}: {key} must name a file inside the model folder, "
                         f"got {name!r}")
    return folder / name


def _joint_covariance(path: Path, tensors: dict[str, torch.Tensor], n_free: int, terms: JointSpaceErrors,
                      n_joints: int) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The optional joint covariance of a model file and the coefficients it covers, checked against
    ``free`` and the folder's joint-space terms; ``(None, None)`` where the file has none."""
    cov, index = tensors.get("joint_covariance"), tensors.get("joint_coefficients")
    if cov is None and index is None:
        return None, None
    if cov is None or index is None:
        raise ModelError(f"{path}: joint_covariance and joint_coefficients go together; one is missing")
    rows = sum(0 if t is None else t.coefficients.shape[0] for t in (terms.compliance, terms.harmonics))
    if (index.dim() != 2 or index.shape[1] != 2 or index.is_floating_point()
            or (index.numel() and (int(index.min()) < 0 or int(index[:, 0].max()) >= rows or int(index[:, 1].max()) >= n_joints))):
        raise ModelError(f"{path}: joint_coefficients must be (K, 2) (row, joint) indices of the model's joint-space terms")
    size = n_free + index.shape[0]
    if tuple(cov.shape) != (size, size):
        raise ModelError(f"{path}: joint_covariance is {tuple(cov.shape)}, expected ({size}, {size}): free parameters "
                         f"and joint-space coefficients")
    return cov, index


def _check_joint_terms(path: Path, meta: dict, n_joints: int) -> None:
    """Refuse joint-space entries of ``calibration.json`` a fit could not have written, in one line naming
    the entry: unknown gravity points, coefficients that are not finite numbers or not one row per point
    (per harmonic term) and one column per joint, a harmonic on the last joint (which has none)."""
    from torchcal.identify.compliance import POINT_FUNCTIONS

    def table(entry: str, values, rows: int | None) -> torch.Tensor:
        try:
            t = torch.tensor(values, dtype=torch.float64)
        except (TypeError, ValueError):
            raise ModelError(f"{path}: {entry} must be a table of numbers") from None
        if t.ndim != 2 or t.shape[1] != n_joints or (rows is not None and t.shape[0] != rows) or not bool(torch.isfinite(t).all()):
            raise ModelError(f"{path}: {entry} must hold finite numbers, {rows if rows is not None else 'a row'} per term "
                             f"and {n_joints} per row (one per joint); got shape {tuple(t.shape)}")
        return t

    compliance = meta.get("gravity_compliance")
    if compliance:
        points = compliance.get("points") if isinstance(compliance, dict) else None
        if not isinstance(points, list) or not all(isinstance(p, str) and p in POINT_FUNCTIONS for p in points):
            raise ModelError(f"{path}: gravity_compliance.points must list points among {sorted(POINT_FUNCTIONS)}, "
                             f"got {points!r}")
        table("gravity_compliance.coefficients_rad_per_m", compliance.get("coefficients_rad_per_m"), len(points))
        point = compliance.get("tcp_point_m")
        if point is not None and (not isinstance(point, list) or len(point) != 3
                                  or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in point)):
            raise ModelError(f"{path}: gravity_compliance.tcp_point_m must be 3 finite numbers (m), got {point!r}")
    harmonics = meta.get("joint_harmonics")
    if harmonics:
        values = harmonics.get("coefficients_rad") if isinstance(harmonics, dict) else None
        t = table("joint_harmonics.coefficients_rad", values, None)
        if t.shape[0] % 2:
            raise ModelError(f"{path}: joint_harmonics.coefficients_rad must hold sine and cosine rows in pairs, got "
                             f"{t.shape[0]} rows")
        if bool((t[:, -1] != 0).any()):
            raise ModelError(f"{path}: joint_harmonics.coefficients_rad has a term on the last joint, which has none")


def load_model(folder: str | Path, device: str | torch.device = "cpu") -> StoredModel:
    """Read a model folder written by :func:`save_model` (safetensors + JSON only).

    The folder is verified first (:func:`torchcal.core.folder.verify_folder`: every file listed in
    ``checksums.json`` with its SHA-256, no file of another result); malformed content is a
    :class:`ModelError` naming the file.
    """
    folder = Path(folder)
    meta_path = folder / "calibration.json"
    if not meta_path.is_file():
        raise ModelError(f"{folder}: not a torchcal model folder (no calibration.json)")
    verify_folder(folder)
    meta = read_json_member(meta_path)
    names = meta.get("parameter_names")
    if not isinstance(names, list):
        raise ModelError(f"{meta_path}: no parameter_names list")
    robot_path = _member_path(folder, meta.get("robot_file"), "robot_file")
    recorded = meta.get("robot_sha256")
    if recorded is not None and sha256_file(robot_path) != recorded:
        # the checksums were recomputed over a robot file of another model: its parameters would not fit it
        raise ModelError(f"{robot_path}: not the robot file this model was fitted with (SHA-256 differs from "
                         f"calibration.json robot_sha256); restore the model folder as it was written")
    tool = meta.get("nominal_tool_mm")  # a URDF has no tool: the one the fit was given is kept here
    robot = load_robot(robot_path, base_link=meta.get("base_link"), end_link=meta.get("end_link"),
                       tool=None if tool is None else (float(tool[0]) * 1e-3, float(tool[1]) * 1e-3, float(tool[2]) * 1e-3))
    tensors = read_tensors(folder / "calibration.safetensors",
                           {"x": 1, "T_reference": 2, "free": 1, "covariance": 2}, finite=("x", "T_reference", "training_q"))
    if tuple(tensors["T_reference"].shape) != (4, 4):
        raise ModelError(f"{folder / 'calibration.safetensors'}: T_reference is not 4x4")
    threshold = meta.get("parallel_threshold_deg", 2.0)
    if not isinstance(threshold, (int, float)) or not math.isfinite(threshold) or threshold < 0:
        raise ModelError(f"{meta_path}: parallel_threshold_deg must be a finite number >= 0, got {threshold!r}")
    with_orientation = meta.get("with_orientation", False)
    if not isinstance(with_orientation, bool):
        raise ModelError(f"{meta_path}: with_orientation must be true or false, got {with_orientation!r}")
    _check_joint_terms(meta_path, meta, robot.dof)
    model = ErrorModel(
        robot,
        with_orientation=with_orientation,
        parallel_threshold_deg=threshold,
        T_instrument_base=tensors["T_reference"],
        device=device,
    )
    if list(model.layout.names) != names:
        raise ModelError(f"{folder}: parameter layout does not match robot {robot.name}")
    if tensors["x"].shape[0] != model.layout.size:
        raise ModelError(f"{folder / 'calibration.safetensors'}: x has {tensors['x'].shape[0]} values, "
                         f"the layout {model.layout.size}")
    free = tensors["free"]
    if free.numel() and (free.is_floating_point() or int(free.min()) < 0 or int(free.max()) >= model.layout.size):
        raise ModelError(f"{folder / 'calibration.safetensors'}: free holds indices outside the parameter layout")
    joint_covariance, joint_coefficients = _joint_covariance(folder / "calibration.safetensors", tensors, len(free),
                                                             JointSpaceErrors.from_metadata(meta), robot.dof)
    stored = StoredModel(
        robot=robot, model=model, x=tensors["x"].to(device), free=free,
        covariance=tensors["covariance"].to(device), metadata=meta, folder=folder,
        training_q=tensors.get("training_q"), joint_covariance=joint_covariance, joint_coefficients=joint_coefficients,
    )
    for name, optional in OPTIONAL_STAGES.items():
        part = optional.load(folder, device)
        if part is not None:
            stored.parts[name] = part
    return stored


def copy_model(src: str | Path, dst: str | Path) -> None:
    """Copy a model folder (used when exporting next to its source)."""
    shutil.copytree(src, dst, dirs_exist_ok=True)


def degrees(v: float) -> float:
    return v * 180.0 / math.pi
