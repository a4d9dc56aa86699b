"""Robot descriptions: the immutable nominal model, read from an MDH YAML or a URDF.

A :class:`RobotModel` holds the nominal kinematics in SI units as an MDH(+beta) table between a
fixed ``base -> frame 0`` transform and a fixed ``frame N -> flange`` transform, plus the
nominal tool point in the ``flange`` frame. For a URDF the structure comes from
pytorch-kinematics and the table from the axis method (:mod:`torchcal.kinematics.axes`);
for a YAML the table is the file's and pytorch-kinematics gets an equivalent URDF, so nominal FK
of both routes can be checked against each other.
"""

from __future__ import annotations

import hashlib
import math
import re
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
import yaml

from torchcal.core.errors import ModelError
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.axes import mdh_from_axes
from torchcal.kinematics.mdh import chain_transforms
from torchcal.kinematics.robot_checks import (
    DuplicateKeyError,
    StrictSafeLoader,
    check_keys,
    check_reach,
    joint_span_problem,
    span_cause,
)

_LENGTH_UNITS = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}
_ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
_ROW_KEYS = ("alpha", "a", "d", "theta")
_OPTIONAL_ROW_KEYS = ("beta", "min", "max", "continuous", "velocity", "acceleration")
#: Keys the YAML may have (``calibration_prior`` is read by :mod:`torchcal.identify.prior`).
_TOP_KEYS = ("name", "kinematics", "calibration_prior")
_KINEMATICS_KEYS = ("convention", "length_unit", "angle_unit", "joints", "tool")


@dataclass(frozen=True)
class RobotModel:
    """Nominal robot kinematics, SI units, float64.

    Attributes:
        name: robot name.
        joint_names: one name per revolute joint, in chain order.
        table: ``(N, 5)`` MDH rows ``[alpha, a, beta, theta_offset, d]`` (rad, m).
        joint_limits: ``(N, 2)`` lower/upper joint limits, rad; ``-inf, +inf`` for a continuous joint
            (a URDF ``type="continuous"`` joint, a YAML row with ``continuous: true``), which has none.
        tool: ``(3,)`` nominal TCP / reflector position in the ``flange`` frame, m.
        T_base_0: ``(4, 4)`` fixed ``base -> frame 0`` transform (identity for a YAML robot).
        T_n_flange: ``(4, 4)`` fixed ``frame N -> flange`` transform (identity for a YAML robot).
        source: file the model was read from, if any.
        urdf: URDF text describing the same chain (for pytorch-kinematics).
        base_link / end_link: URDF link names of ``base`` and ``flange``.
        velocity_limits / acceleration_limits: ``(N,)`` joint speed (rad/s) and acceleration
            (rad/s^2) limits where the YAML gives them for every joint, else ``None``.
    """

    name: str
    joint_names: tuple[str, ...]
    table: torch.Tensor
    joint_limits: torch.Tensor
    tool: torch.Tensor
    T_base_0: torch.Tensor = field(default_factory=lambda: torch.eye(4, dtype=torch.float64))
    T_n_flange: torch.Tensor = field(default_factory=lambda: torch.eye(4, dtype=torch.float64))
    source: str | None = None
    urdf: str | None = None
    base_link: str = "base"
    end_link: str = "flange"
    velocity_limits: torch.Tensor | None = None
    acceleration_limits: torch.Tensor | None = None

    @property
    def dof(self) -> int:
        return int(self.table.shape[0])

    def flange_pose(self, q: torch.Tensor) -> torch.Tensor:
        """Nominal ``T_base_flange`` ``(..., 4, 4)`` for joint angles ``q`` ``(..., N)`` in rad."""
        table = self.table.to(q)
        rot, pos = chain_transforms(q, table)
        return self.T_base_0.to(q) @ tf.homogeneous(rot, pos) @ self.T_n_flange.to(q)

    def tcp_position(self, q: torch.Tensor) -> torch.Tensor:
        """Nominal TCP position in ``base`` ``(..., 3)``, m."""
        pose = self.flange_pose(q)
        return pose[..., :3, :3] @ self.tool.to(q) + pose[..., :3, 3]

    @property
    def continuous(self) -> torch.Tensor:
        """``(N,)`` bool: joints without limits (any angle is reachable)."""
        return ~torch.isfinite(self.joint_limits).all(-1)

    @property
    def turn_limits(self) -> torch.Tensor:
        """``(N, 2)`` rad: the joint limits with one turn ``[-pi, pi]`` for a continuous joint.

        For what needs a finite range: sampling poses, scaling features, centring a planner; a
        continuous joint's configurations repeat every turn, so one turn covers all of them.
        """
        turn = torch.tensor([-math.pi, math.pi], dtype=self.joint_limits.dtype)
        return torch.where(self.continuous.unsqueeze(-1), turn, self.joint_limits)

    def within_limits(self, q: torch.Tensor, tol: float = 1e-9) -> torch.Tensor:
        lim = self.joint_limits.to(q)
        return ((q >= lim[:, 0] - tol) & (q <= lim[:, 1] + tol)).all(-1)

    def sample_joints(self, n: int, generator: torch.Generator, margin: float = 0.0) -> torch.Tensor:
        """Uniform random joint angles ``(n, N)`` within limits (shrunk by ``margin`` rad); one turn
        ``[-pi, pi]`` for a continuous joint."""
        lim = self.turn_limits
        lo = lim[:, 0] + torch.where(self.continuous, 0.0, margin)
        hi = lim[:, 1] - torch.where(self.continuous, 0.0, margin)
        u = torch.rand(n, self.dof, generator=generator, dtype=torch.float64)
        return lo + u * (hi - lo)

    def pk_chain(self, dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu"):
        """The pytorch-kinematics serial chain of this robot (structure and nominal FK)."""
        import pytorch_kinematics as pk

        text = self.urdf if self.urdf is not None else mdh_to_urdf(self)
        chain = pk.build_serial_chain_from_urdf(text.encode(), self.end_link, self.base_link)
        return chain.to(dtype=dtype, device=device)


# ---------------------------------------------------------------------------------------- YAML


def _number(value, path: Path, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ModelError(f"{path}: {where} must be a number, got {value!r}")
    if not math.isfinite(float(value)):
        raise ModelError(f"{path}: {where} must be finite, got {value!r}")
    return float(value)


#: Largest robot file read (bytes): a robot description is a few kB; a URDF with meshes inline a few MB.
MAX_ROBOT_FILE_BYTES = 16 * 1024 * 1024
#: Most YAML aliases (``*name``) a robot file may use: each may stand for a whole tree (alias bombs).
MAX_YAML_ALIASES = 32


def read_robot_text(path: Path) -> str:
    """The UTF-8 text of a robot file, refused when larger than :data:`MAX_ROBOT_FILE_BYTES` or not text."""
    size = path.stat().st_size
    if size > MAX_ROBOT_FILE_BYTES:
        raise ModelError(f"{path}: {size} bytes; a robot file may have at most {MAX_ROBOT_FILE_BYTES}")
    data = path.read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ModelError(f"{path}: line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x})") from None


class _LimitedLoader(StrictSafeLoader):
    """A :class:`StrictSafeLoader` (no duplicate keys, ``455e0`` a number) that refuses more than
    :data:`MAX_YAML_ALIASES` aliases."""

    aliases = 0

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            self.aliases += 1
            if self.aliases > MAX_YAML_ALIASES:
                mark = self.peek_event().start_mark
                raise yaml.YAMLError(f"more than {MAX_YAML_ALIASES} aliases (line {mark.line + 1})")
        return super().compose_node(parent, index)


def _robot_name(value: object, path: Path) -> str:
    """The robot's ``name``: a scalar of at most 200 characters."""
    if not isinstance(value, (str, int, float)) or isinstance(value, bool) or len(str(value)) > 200:
        raise ModelError(f"{path}: name must be a short text (at most 200 characters)")
    return str(value)


def robot_from_yaml(path: str | Path) -> RobotModel:
    """Read a robot YAML of the data contract (``kinematics.convention: mdh``)."""
    path = Path(path)
    text = read_robot_text(path)
    try:
        doc = yaml.load(text, Loader=_LimitedLoader)  # a SafeLoader with an alias limit
    except DuplicateKeyError as exc:
        raise ModelError(f"{path}: {exc}") from None
    except yaml.YAMLError as exc:
        detail = str(exc).splitlines()[0] if "aliases" in str(exc) else exc.__class__.__name__
        raise ModelError(f"{path}: not valid YAML ({detail})") from None
    except RecursionError:
        raise ModelError(f"{path}: not a robot file (YAML nested too deeply to read)") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("kinematics"), dict):
        raise ModelError(f"{path}: expected a mapping with a 'kinematics' section")
    check_keys(doc, _TOP_KEYS, path, "the top level")
    kin = doc["kinematics"]
    check_keys(kin, _KINEMATICS_KEYS, path, "kinematics")
    convention = str(kin.get("convention", "")).lower()
    if convention != "mdh":
        raise ModelError(
            f"{path}: kinematics.convention is {kin.get('convention')!r}; only 'mdh' "
            "(Craig's modified DH) is supported in YAML. Give a URDF for other descriptions."
        )
    length_unit = str(kin.get("length_unit", "mm"))
    angle_unit = str(kin.get("angle_unit", "deg"))
    if length_unit not in _LENGTH_UNITS:
        raise ModelError(f"{path}: kinematics.length_unit {length_unit!r} is not one of {sorted(_LENGTH_UNITS)}")
    if angle_unit not in _ANGLE_UNITS:
        raise ModelError(f"{path}: kinematics.angle_unit {angle_unit!r} is not one of {sorted(_ANGLE_UNITS)}")
    ls, as_ = _LENGTH_UNITS[length_unit], _ANGLE_UNITS[angle_unit]
    joints = kin.get("joints")
    if not isinstance(joints, list) or not joints:
        raise ModelError(f"{path}: kinematics.joints must be a non-empty list of rows")
    rows, limits, velocities, accelerations = [], [], [], []
    for i, row in enumerate(joints, start=1):
        if not isinstance(row, dict):
            raise ModelError(f"{path}: joint {i} must be a mapping with keys {_ROW_KEYS}")
        check_keys(row, _ROW_KEYS + _OPTIONAL_ROW_KEYS, path, f"joint {i}")
        missing = [k for k in _ROW_KEYS if k not in row]
        if missing:
            raise ModelError(f"{path}: joint {i} lacks {missing}")
        alpha, a, d, theta = (_number(row[k], path, f"joint {i} '{k}'") for k in _ROW_KEYS)
        beta = _number(row.get("beta", 0.0), path, f"joint {i} 'beta'")
        continuous = row.get("continuous", False)
        if not isinstance(continuous, bool):
            raise ModelError(f"{path}: joint {i} 'continuous' must be true or false, got {continuous!r}")
        if continuous:
            if "min" in row or "max" in row:
                raise ModelError(f"{path}: joint {i} is continuous and has min/max: give one or the other")
            lo, hi = -math.inf, math.inf
        else:
            lo = _number(row.get("min", -180.0 if angle_unit == "deg" else -math.pi), path, f"joint {i} 'min'")
            hi = _number(row.get("max", 180.0 if angle_unit == "deg" else math.pi), path, f"joint {i} 'max'")
        if lo >= hi:
            raise ModelError(f"{path}: joint {i} has min {lo} >= max {hi}")
        if not continuous and joint_span_problem(lo * as_, hi * as_):
            raise ModelError(f"{path}: joint {i} 'min'/'max' {lo:g}..{hi:g} {angle_unit}: {span_cause(lo, hi, angle_unit)}")
        rows.append([alpha * as_, a * ls, beta * as_, theta * as_, d * ls])
        limits.append([lo * as_, hi * as_])
        if "velocity" in row:
            velocities.append(_number(row["velocity"], path, f"joint {i} 'velocity'") * as_)
        if "acceleration" in row:
            accelerations.append(_number(row["acceleration"], path, f"joint {i} 'acceleration'") * as_)
    tool = kin.get("tool", [0.0, 0.0, 0.0])
    if not isinstance(tool, list) or len(tool) != 3:
        raise ModelError(f"{path}: kinematics.tool must be a list of 3 numbers [x, y, z]")
    tool_m = [_number(v, path, "kinematics.tool") * ls for v in tool]
    n = len(rows)
    robot = RobotModel(
        name=_robot_name(doc.get("name", path.stem), path),
        joint_names=tuple(f"joint{i}" for i in range(1, n + 1)),
        table=torch.tensor(rows, dtype=torch.float64),
        joint_limits=torch.tensor(limits, dtype=torch.float64),
        tool=torch.tensor(tool_m, dtype=torch.float64),
        source=str(path),
        velocity_limits=torch.tensor(velocities, dtype=torch.float64) if len(velocities) == n else None,
        acceleration_limits=torch.tensor(accelerations, dtype=torch.float64) if len(accelerations) == n else None,
    )
    check_reach(robot, path, length_unit, _LENGTH_UNITS)  # values in mm under length_unit: m, or the reverse
    return robot


def robot_to_yaml(robot: RobotModel, table: torch.Tensor | None = None, tool: torch.Tensor | None = None) -> str:
    """A contract YAML (mm, deg) of ``robot``, optionally with a calibrated ``table`` and ``tool``.

    ``beta`` is written only where it is non-zero (YAML readers of the contract ignore nothing:
    torchcal reads it back).
    """
    table = robot.table if table is None else table
    tool = robot.tool if tool is None else tool
    deg = 180.0 / math.pi
    lines = [
        f"name: {robot.name}",
        "kinematics:",
        "  convention: mdh",
        "  length_unit: mm",
        "  angle_unit: deg",
        "  joints:",
    ]
    velocities = robot.velocity_limits.tolist() if robot.velocity_limits is not None else [None] * robot.dof
    accelerations = robot.acceleration_limits.tolist() if robot.acceleration_limits is not None else [None] * robot.dof
    for row, lim, velocity, acceleration in zip(table.tolist(), robot.joint_limits.tolist(), velocities, accelerations):
        alpha, a, beta, theta, d = row
        entries = [f"alpha: {alpha * deg:.9g}", f"a: {a * 1e3:.9g}", f"d: {d * 1e3:.9g}", f"theta: {theta * deg:.9g}"]
        if abs(beta) > 0:
            entries.append(f"beta: {beta * deg:.9g}")
        if math.isfinite(lim[0]) and math.isfinite(lim[1]):
            entries += [f"min: {lim[0] * deg:.9g}", f"max: {lim[1] * deg:.9g}"]
        else:
            entries.append("continuous: true")
        if velocity is not None:
            entries.append(f"velocity: {velocity * deg:.9g}")
        if acceleration is not None:
            entries.append(f"acceleration: {acceleration * deg:.9g}")
        lines.append("    - {" + ", ".join(entries) + "}")
    lines.append("  tool: [" + ", ".join(f"{v * 1e3:.9g}" for v in tool.tolist()) + "]")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------- URDF


def _rpy(rotation: torch.Tensor) -> list[float]:
    return tf.matrix_to_euler_xyz(rotation).tolist()


def _origin_xml(transform: torch.Tensor) -> str:
    xyz = " ".join(f"{v:.17g}" for v in transform[:3, 3].tolist())
    rpy = " ".join(f"{v:.17g}" for v in _rpy(transform[:3, :3]))
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'


def mdh_to_urdf(robot: RobotModel) -> str:
    """A URDF of the nominal chain: one revolute joint about z per MDH row.

    Joint ``i``'s origin is ``Rx(alpha) Tx(a) Ry(beta) Rz(theta_offset) Tz(d)``; since ``Rz`` and
    ``Tz`` commute, the joint rotation about its own z completes the MDH link transform.
    """
    zero = torch.zeros(1, dtype=torch.float64)
    links = [f'<link name="{robot.base_link}"/>']
    joints = []
    parent = robot.base_link
    for i, row in enumerate(robot.table):
        rot, pos = chain_transforms(zero, row.unsqueeze(0))
        link_tf = tf.homogeneous(rot, pos)
        if i == 0:
            link_tf = robot.T_base_0 @ link_tf
        child = f"link{i + 1}"
        lo, hi = robot.joint_limits[i].tolist()
        links.append(f'<link name="{child}"/>')
        kind, limit = ("continuous", "") if bool(robot.continuous[i]) else (
            "revolute", f'<limit lower="{lo:.17g}" upper="{hi:.17g}" effort="0" velocity="0"/>')
        joints.append(
            f'<joint name="{robot.joint_names[i]}" type="{kind}"><parent link="{parent}"/>'
            f'<child link="{child}"/>{_origin_xml(link_tf)}<axis xyz="0 0 1"/>{limit}</joint>'
        )
        parent = child
    links.append(f'<link name="{robot.end_link}"/>')
    joints.append(
        f'<joint name="flange_joint" type="fixed"><parent link="{parent}"/>'
        f'<child link="{robot.end_link}"/>{_origin_xml(robot.T_n_flange)}</joint>'
    )
    body = "\n  ".join(links + joints)
    return f'<?xml version="1.0"?>\n<robot name="{robot.name}">\n  {body}\n</robot>\n'


def _joint_origins_float64(text: str) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Joint origin transforms ``parent -> joint frame`` of a URDF, float64, and the URDF joint
    types (``revolute``, ``continuous``, ...), by joint name."""
    from pytorch_kinematics.urdf_parser_py.urdf import URDF

    robot = URDF.from_xml_string(text.encode() if isinstance(text, str) else text)
    origins, types = {}, {}
    for joint in robot.joints:
        xyz = joint.origin.xyz if joint.origin is not None and joint.origin.xyz is not None else [0, 0, 0]
        rpy = joint.origin.rpy if joint.origin is not None and joint.origin.rpy is not None else [0, 0, 0]
        rot = tf.euler_xyz_to_matrix(torch.tensor(rpy, dtype=torch.float64))
        origins[joint.name] = tf.homogeneous(rot, torch.tensor(xyz, dtype=torch.float64))
        types[joint.name] = joint.type
    return origins, types


@dataclass(frozen=True)
class _ParsedUrdf:
    """What a URDF gives for one chain (see :func:`robot_from_urdf`), cached by the text's hash."""

    joint_names: tuple[str, ...]
    table: torch.Tensor
    T_base_0: torch.Tensor
    T_n_flange: torch.Tensor
    limits: torch.Tensor
    base_link: str
    end_link: str
    notes: tuple[str, ...]  # what the URDF parser said (unknown tags and attributes)


#: Parsed URDFs by (sha256 of the text, base_link, end_link): a fit loads its robot several times
#: (the command, the model folder it writes, the folder's checks), and each parse runs the URDF
#: parser three times (pytorch-kinematics' full and serial chains, the float64 origins).
_URDF_CACHE: dict[tuple[str, str | None, str | None], _ParsedUrdf] = {}
_URDF_CACHE_SIZE = 8


@contextmanager
def _parser_notes() -> Iterator[list[str]]:
    """Collect what the URDF parser of pytorch-kinematics writes to stderr (one line per unknown tag
    or attribute, per parse) instead of letting it print."""
    from pytorch_kinematics.urdf_parser_py import xml_reflection
    from pytorch_kinematics.urdf_parser_py.xml_reflection import core

    notes: list[str] = []
    saved = core.on_error, xml_reflection.on_error
    core.on_error = xml_reflection.on_error = notes.append
    try:
        yield notes
    finally:
        core.on_error, xml_reflection.on_error = saved


def _notes_warning(path: Path, notes: tuple[str, ...]) -> str:
    """One line for the parser's notes: what was skipped, each kind once (a misspelt attribute,
    ``rpi`` for ``rpy``, reads as absent, so they are named)."""
    kinds: dict[str, int] = {}
    for note in notes:
        match = re.match(r'(Unknown (?:tag|attribute) "[^"]*")', note)
        kind = match.group(1) if match else note
        kinds[kind] = kinds.get(kind, 0) + 1
    listed = "; ".join(f"{kind} x{n}" if n > 1 else kind for kind, n in list(kinds.items())[:6])
    more = f"; and {len(kinds) - 6} more kinds" if len(kinds) > 6 else ""
    return (f"{path}: the URDF parser skipped {len(notes)} element(s) it does not know, read as absent "
            f"({listed}{more}); kinematics use links, joints, origins, axes and limits only")


def robot_from_urdf(
    path: str | Path,
    *,
    base_link: str | None = None,
    end_link: str | None = None,
    tool: tuple[float, float, float] | None = None,
) -> RobotModel:
    """Read a URDF (m, rad) through pytorch-kinematics and derive its MDH(+beta) table.

    Args:
        path: URDF file.
        base_link: link that is the ``base`` frame (default: the URDF root).
        end_link: link that is the ``flange`` frame (default: the last link of the chain).
        tool: nominal TCP in the ``flange`` frame, m (default: the flange origin).

    The text is parsed once per content and chain (cached by its sha256); what the parser says
    about unknown tags and attributes becomes one warning, at that parse.
    """
    path = Path(path)
    text = read_robot_text(path)
    key = (hashlib.sha256(text.encode()).hexdigest(), base_link, end_link)
    parsed = _URDF_CACHE.get(key)
    if parsed is None:
        with _parser_notes() as notes:
            parsed = _parse_urdf(path, text, base_link, end_link)
        # each of the three parses says the same: each line once
        parsed = replace(parsed, notes=tuple(dict.fromkeys(notes)))
        while len(_URDF_CACHE) >= _URDF_CACHE_SIZE:
            _URDF_CACHE.pop(next(iter(_URDF_CACHE)))
        # also under the links it resolved to: a model folder names them when it loads its copy
        for k in (key, (key[0], parsed.base_link, parsed.end_link)):
            _URDF_CACHE[k] = parsed
        if parsed.notes:  # once per text: its copy in a model folder says nothing new
            warnings.warn(_notes_warning(path, parsed.notes), stacklevel=2)
    robot = RobotModel(
        name=path.stem,
        joint_names=parsed.joint_names,
        table=parsed.table.clone(),
        joint_limits=parsed.limits.clone(),
        tool=torch.tensor(tool if tool is not None else (0.0, 0.0, 0.0), dtype=torch.float64),
        T_base_0=parsed.T_base_0.clone(),
        T_n_flange=parsed.T_n_flange.clone(),
        source=str(path),
        urdf=text,
        base_link=parsed.base_link,
        end_link=parsed.end_link,
    )
    check_reach(robot, path, None, {})  # origins in mm where URDF expects m
    return robot


def _parse_urdf(path: Path, text: str, base_link: str | None, end_link: str | None) -> _ParsedUrdf:
    """The chain from ``base_link`` to ``end_link`` of URDF ``text`` (``path`` names it in errors)."""
    import pytorch_kinematics as pk

    try:
        full = pk.build_chain_from_urdf(text.encode())
    except Exception as exc:  # noqa: BLE001 (the parser raises many types; the user needs the file name)
        raise ModelError(f"{path}: cannot parse URDF ({exc})") from None
    names = full.get_frame_names(exclude_fixed=False)
    root = full._root.name if hasattr(full, "_root") else names[0]
    base_link = base_link or root
    if end_link is None:
        end_link = names[-1]
    for label, link in (("base_link", base_link), ("end_link", end_link)):
        if link not in names:
            raise ModelError(f"{path}: {label} '{link}' is not a link of this URDF (links: {', '.join(names)})")
    try:
        chain = pk.SerialChain(full, end_link, base_link)  # from the parsed chain: no second parse
    except Exception as exc:  # noqa: BLE001 (as above)
        raise ModelError(f"{path}: no serial chain from '{base_link}' to '{end_link}' ({exc})") from None
    chain = chain.to(dtype=torch.float64)
    joint_names = tuple(chain.get_joint_parameter_names())
    if not joint_names:
        raise ModelError(f"{path}: no movable joint between '{base_link}' and '{end_link}'")
    frames = chain.get_joints()
    for joint in frames:
        if joint.joint_type != "revolute":
            raise ModelError(f"{path}: joint '{joint.name}' is {joint.joint_type}; only revolute joints are supported")
    # pytorch-kinematics gives the chain's structure; its URDF reader rounds rpy to float32
    # (about 1e-8 m at arm's length), so the origins are re-read in float64 by joint name.
    origins, urdf_types = _joint_origins_float64(text)
    transform = torch.eye(4, dtype=torch.float64)
    points, directions = [], []
    for frame in chain._serial_frames[1:]:
        origin = origins[frame.joint.name]
        if not bool(torch.isfinite(origin).all()):
            raise ModelError(f"{path}: joint '{frame.joint.name}': origin xyz/rpy must be finite numbers")
        transform = transform @ origin
        if frame.joint.joint_type == "fixed":
            continue
        axis = frame.joint.axis.to(torch.float64)
        if not bool(torch.isfinite(axis).all()) or float(axis.norm()) < 1e-9:
            raise ModelError(f"{path}: joint '{frame.joint.name}': axis must be a finite, non-zero vector, "
                             f"got {axis.tolist()}")
        points.append(transform[:3, 3])
        directions.append(transform[:3, :3] @ axis)
    T_base_flange = transform
    try:
        axes = mdh_from_axes(torch.stack(points), torch.stack(directions), T_base_flange)
    except (RuntimeError, ValueError, ArithmeticError) as exc:  # LinAlgError is a RuntimeError
        raise ModelError(f"{path}: the joint axes give no MDH table ({exc.__class__.__name__}: {exc})") from None
    limits = []
    for joint in frames:
        if urdf_types.get(joint.name) == "continuous":
            # no limits: the URDF ignores a continuous joint's lower/upper (pytorch-kinematics reads
            # it as revolute, with the limit tag's lower/upper, or (0, 0) where it gives only effort)
            limits.append([-math.inf, math.inf])
            continue
        lim = joint.limits
        if lim is not None and not (math.isfinite(float(lim[0])) and math.isfinite(float(lim[1]))
                                    and float(lim[0]) < float(lim[1])):
            # a NaN limit would switch every range check off without a word
            raise ModelError(f"{path}: joint '{joint.name}': <limit lower/upper> must be finite numbers with "
                             f"lower < upper, got {float(lim[0])!r}, {float(lim[1])!r}")
        if lim is not None and joint_span_problem(float(lim[0]), float(lim[1])):  # degrees read as radians
            lo, hi = float(lim[0]), float(lim[1])
            raise ModelError(f"{path}: joint '{joint.name}': <limit lower/upper> {lo:g}, {hi:g} rad: "
                             f"{span_cause(lo, hi, None)}")
        limits.append([float(lim[0]), float(lim[1])] if lim is not None else [-math.pi, math.pi])
    return _ParsedUrdf(joint_names=joint_names, table=axes.table, T_base_0=axes.T_base_0, T_n_flange=axes.T_n_flange,
                       limits=torch.tensor(limits, dtype=torch.float64), base_link=base_link, end_link=end_link, notes=())


def load_robot(
    path: str | Path,
    *,
    base_link: str | None = None,
    end_link: str | None = None,
    tool: tuple[float, float, float] | None = None,
) -> RobotModel:
    """Load a robot from a contract YAML (``.yaml``/``.yml``) or a URDF (``.urdf``/``.xml``)."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: robot file not found")
    suffix = path.suffix.lower()
    if suffix in (".yaml", ".yml"):
        return robot_from_yaml(path)
    if suffix in (".urdf", ".xml"):
        return robot_from_urdf(path, base_link=base_link, end_link=end_link, tool=tool)
    raise ModelError(f"{path}: unknown robot format '{suffix}' (expected .yaml, .yml or .urdf)")


def default_robot_path() -> Path:
    """The embedded digital-twin robot YAML."""
    return Path(__file__).resolve().parent.parent / "resources" / "robots" / "twin-kr6.yaml"
