"""The calibrated URDF: the user's own URDF with only its joint origins changed.

ROS / MoveIt users run their robot from a URDF. A calibrated geometry (an MDH+beta table and a
tool point) is written back into that file without touching anything else: every link, visual,
collision, inertial, limit, axis, mimic and extension stays as it was, and only the ``<origin>`` of
each moving joint of the calibrated chain changes. The calibrated tool is added as one fixed joint
and link after the end link (the flange stays where the robot's software expects it).

How the origins are found (all frames at the zero configuration, in the ``base`` link):

* ``F_i``: MDH frame ``i`` of the table (``T_base_0 A_1 ... A_i``); ``K_i``: the child link of the
  URDF's ``i``-th moving joint. The axis method (:mod:`torchcal.kinematics.axes`) puts ``F_i``'s z
  on that joint's axis through a point of it, so ``C_i = F_i^-1 K_i`` of the nominal robot is a
  constant that turns with the joint: ``K_i(q) = F_i(q) C_i`` for every ``q``.
* With the calibrated table ``F'_i``, the calibrated child frame is ``K'_i = F'_i C_i``: the links
  (and their meshes) ride on the calibrated joint axes as they rode on the nominal ones, joint
  zero offsets folded in.
* Walking the chain from the base link, fixed joints keep their origins and each moving joint's
  origin becomes ``P'^-1 K'_i`` (``P'`` the calibrated pose of its parent link). The fixed joints
  after the last moving joint are unchanged, since ``T_n_flange`` is not a calibration parameter.

An MDH (YAML) robot gets the same treatment on the URDF generated from its nominal table
(:func:`torchcal.kinematics.robot.mdh_to_urdf`). The XML is read and written with
:mod:`xml.etree.ElementTree` (comments kept); numbers are written with 17 significant digits, so a
float64 reader reproduces the calibrated chain to rounding (~1e-15 m).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.mdh import link_transform
from torchcal.kinematics.robot import RobotModel, mdh_to_urdf

#: Joint types that move (URDF); ``fixed`` joints keep their origins.
MOVING = ("revolute", "continuous")
#: Largest deviation (m, rad) of a nominal joint frame from its MDH frame's z axis that is accepted.
AXIS_TOLERANCE = 1e-6


def _parse(text: str) -> ET.Element:
    parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
    try:
        return ET.fromstring(text, parser=parser)
    except ET.ParseError as exc:
        raise ModelError(f"the robot URDF is not valid XML ({exc})") from None


def _floats(text: str | None, default: tuple[float, float, float]) -> list[float]:
    return [float(v) for v in text.split()] if text else list(default)


def origin_matrix(joint: ET.Element) -> torch.Tensor:
    """``(4, 4)`` float64 transform of a ``<joint>``'s ``<origin>`` (identity without one)."""
    origin = joint.find("origin")
    xyz = _floats(None if origin is None else origin.get("xyz"), (0.0, 0.0, 0.0))
    rpy = _floats(None if origin is None else origin.get("rpy"), (0.0, 0.0, 0.0))
    rot = tf.euler_xyz_to_matrix(torch.tensor(rpy, dtype=torch.float64))
    return tf.homogeneous(rot, torch.tensor(xyz, dtype=torch.float64))


def rpy_of(rotation: torch.Tensor) -> list[float]:
    """URDF ``rpy`` (fixed-axis XYZ, rad) of a rotation matrix, well conditioned at every pitch.

    ``pitch = atan2(-r20, hypot(r00, r10))`` instead of ``asin``, which loses half the digits near
    +-90 deg; at the singularity the roll is set to 0 and the yaw takes the whole turn.
    """
    r = rotation.tolist()
    cos_pitch = math.hypot(r[0][0], r[1][0])
    pitch = math.atan2(-r[2][0], cos_pitch)
    if cos_pitch > 1e-12:
        return [math.atan2(r[2][1], r[2][2]), pitch, math.atan2(r[1][0], r[0][0])]
    return [0.0, pitch, math.atan2(-r[0][1], r[1][1])]


def _set_origin(joint: ET.Element, transform: torch.Tensor) -> None:
    origin = joint.find("origin")
    if origin is None:  # an origin-less joint gets one right after its child element (order is free in URDF)
        origin = ET.Element("origin")
        joint.insert(0, origin)
    origin.set("xyz", " ".join(repr(float(v)) for v in transform[:3, 3].tolist()))
    origin.set("rpy", " ".join(repr(v) for v in rpy_of(transform[:3, :3])))


def chain_joints(root: ET.Element, base_link: str, end_link: str) -> list[ET.Element]:
    """The ``<joint>`` elements from ``base_link`` to ``end_link``, base first."""
    by_child: dict[str, ET.Element] = {}
    for joint in root.findall("joint"):
        child = joint.find("child")
        if child is not None and child.get("link"):
            by_child[str(child.get("link"))] = joint
    chain, link = [], end_link
    while link != base_link:
        found = by_child.get(link)
        parent = None if found is None else found.find("parent")
        if found is None or parent is None:
            raise ModelError(f"the robot URDF has no joint chain from '{base_link}' to '{end_link}'")
        chain.append(found)
        link = str(parent.get("link"))
        if len(chain) > len(by_child):
            raise ModelError(f"the robot URDF's joints form a loop above '{end_link}'")
    return chain[::-1]


def _mdh_frames(robot: RobotModel, table: torch.Tensor) -> list[torch.Tensor]:
    """MDH frames ``F_1..F_N`` ``(4, 4)`` at zero joints in ``base`` for ``table`` ``(N, 5)``."""
    frames, pose = [], robot.T_base_0.to(torch.float64)
    for row in table.to(torch.float64):
        rot, pos = link_transform(*row.unbind(-1))
        pose = pose @ tf.homogeneous(rot, pos)
        frames.append(pose)
    return frames


def _comment_text(lines: list[str]) -> str:
    # "--" may not appear inside an XML comment
    return "\n  " + "\n  ".join(line.replace("--", "- -") for line in lines) + "\n  "


def unique_name(root: ET.Element, tag: str, wanted: str) -> str:
    """``wanted``, or ``wanted_2``, ``_3``... if a ``<tag>`` of that name exists."""
    taken = {str(e.get("name")) for e in root.findall(tag)}
    name, k = wanted, 2
    while name in taken:
        name, k = f"{wanted}_{k}", k + 1
    return name


def calibrated_urdf(robot: RobotModel, table: torch.Tensor, flange_from_tool: torch.Tensor,
                    notes: list[str]) -> tuple[str, str]:
    """The calibrated URDF text and the name of its TCP link.

    Args:
        robot: the nominal robot (its own URDF, or the one generated from its MDH table).
        table: ``(N, 5)`` calibrated MDH+beta rows (rad, m).
        flange_from_tool: ``(4, 4)`` calibrated ``T_flange_tool`` (m).
        notes: lines of the XML comment put first in ``<robot>`` (what the file cannot hold).
    """
    root = _parse(robot.urdf if robot.urdf is not None else mdh_to_urdf(robot))
    joints = chain_joints(root, robot.base_link, robot.end_link)
    moving = [j for j in joints if j.get("type") in MOVING]
    if len(moving) != robot.dof:
        raise ModelError(f"the robot URDF has {len(moving)} moving joints from '{robot.base_link}' to "
                         f"'{robot.end_link}', the model {robot.dof}")
    nominal = _mdh_frames(robot, robot.table)
    calibrated = _mdh_frames(robot, table.detach().cpu())
    pose = torch.eye(4, dtype=torch.float64)
    offsets: list[torch.Tensor] = []  # C_i = F_i^-1 K_i of the nominal robot
    for joint in joints:
        pose = pose @ origin_matrix(joint)
        if joint.get("type") in MOVING:
            i = len(offsets)
            c = tf.invert(nominal[i]) @ pose
            axis_element = joint.find("axis")
            axis = torch.tensor(_floats(None if axis_element is None else axis_element.get("xyz"), (1.0, 0.0, 0.0)),
                                dtype=torch.float64)
            axis = c[:3, :3] @ (axis / axis.norm())
            off_axis = max(float(c[:2, 3].abs().max()), float((axis - torch.tensor([0.0, 0.0, 1.0],
                                                                                  dtype=torch.float64)).abs().max()))
            if off_axis > AXIS_TOLERANCE:
                raise ModelError(f"joint '{joint.get('name')}': its axis is not MDH frame {i + 1}'s z "
                                 f"(off by {off_axis:.2e}); the calibrated URDF cannot be written")
            offsets.append(c)
    pose, i = torch.eye(4, dtype=torch.float64), 0
    for joint in joints:
        if joint.get("type") in MOVING:
            target = calibrated[i] @ offsets[i]
            i += 1
            _set_origin(joint, tf.invert(pose) @ target)
            pose = target
        else:
            pose = pose @ origin_matrix(joint)
    tcp_link = unique_name(root, "link", f"{robot.end_link}_calibrated_tcp")
    tcp_joint = ET.SubElement(root, "joint", {"name": unique_name(root, "joint", f"{tcp_link}_joint"),
                                              "type": "fixed"})
    ET.SubElement(tcp_joint, "parent", {"link": robot.end_link})
    ET.SubElement(tcp_joint, "child", {"link": tcp_link})
    _set_origin(tcp_joint, flange_from_tool.detach().cpu().to(torch.float64))
    tcp_joint.tail = "\n"
    ET.SubElement(root, "link", {"name": tcp_link}).tail = "\n"
    comment = ET.Comment(_comment_text(notes))
    comment.tail = "\n  "
    root.insert(0, comment)
    text = ET.tostring(root, encoding="unicode")
    return '<?xml version="1.0"?>\n' + text + "\n", tcp_link
