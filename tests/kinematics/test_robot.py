"""Robot models: YAML and URDF routes agree; pytorch-kinematics gives the same structure."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from tests.conftest import REAL_DATA
from torchcal.core.errors import ModelError
from torchcal.kinematics.robot import load_robot, mdh_to_urdf, robot_to_yaml


def test_yaml_and_urdf_of_the_same_robot_agree_to_1e_9_m(robot, tmp_path, generator):
    urdf = tmp_path / "twin.urdf"
    urdf.write_text(mdh_to_urdf(robot))
    from_urdf = load_robot(urdf)
    q = robot.sample_joints(500, generator)
    diff = (from_urdf.flange_pose(q) - robot.flange_pose(q))[..., :3, :].abs().max()
    assert diff < 1e-9
    assert from_urdf.joint_names == tuple(f"joint{i}" for i in range(1, 7))
    assert torch.allclose(from_urdf.joint_limits, robot.joint_limits)


def test_pytorch_kinematics_chain_matches_mdh_fk(robot, generator):
    # pytorch-kinematics 0.10 parses URDF rpy in float32: agreement to ~1e-7 m, not better.
    chain = robot.pk_chain()
    q = robot.sample_joints(200, generator)
    pk_pose = chain.forward_kinematics(q).get_matrix()
    assert (pk_pose - robot.flange_pose(q)).abs().max() < 1e-6
    assert len(chain.get_joint_parameter_names()) == robot.dof


def test_yaml_round_trip(robot, tmp_path):
    path = tmp_path / "r.yaml"
    path.write_text(robot_to_yaml(robot))
    again = load_robot(path)
    assert torch.allclose(again.table, robot.table, atol=1e-12)
    assert torch.allclose(again.tool, robot.tool)


def test_speed_and_acceleration_limits_read_and_round_trip(robot, tmp_path):
    text = robot_to_yaml(robot).replace("max: 170}", "max: 170, velocity: 360, acceleration: 1500}")
    rows = [f"max: {m}" for m in ("45", "156", "185", "120", "350")]
    for row, (v, a) in zip(rows, ((300, 1400), (360, 2000), (381, 3000), (388, 3000), (615, 4000))):
        text = text.replace(f"{row}}}", f"{row}, velocity: {v}, acceleration: {a}}}")
    path = tmp_path / "limits.yaml"
    path.write_text(text)
    loaded = load_robot(path)
    expected = torch.tensor([1500, 1400, 2000, 3000, 3000, 4000], dtype=torch.float64) * math.pi / 180
    torch.testing.assert_close(loaded.acceleration_limits, expected)
    assert loaded.velocity_limits is not None and float(loaded.velocity_limits[0]) == pytest.approx(2 * math.pi)
    path.write_text(robot_to_yaml(loaded))
    torch.testing.assert_close(load_robot(path).acceleration_limits, expected)
    assert robot.acceleration_limits is None  # the embedded twin gives none: the motion defaults apply


def test_urdf_with_non_z_axes_and_offsets_matches_its_own_fk(tmp_path, generator):
    """A UR-like URDF with axes along y and rotated origins: the derived MDH model reproduces the URDF FK."""
    urdf = """<?xml version="1.0"?><robot name="toy">
    <link name="world"/><link name="l1"/><link name="l2"/><link name="l3"/><link name="tool0"/>
    <joint name="j1" type="revolute"><parent link="world"/><child link="l1"/><origin xyz="0.1 0 0.2" rpy="0 0 0.3"/>
      <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
    <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0 0.13 0.05" rpy="0 1.5707963267948966 0"/>
      <axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
    <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/><origin xyz="0 -0.1 0.4" rpy="0 0 0"/>
      <axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
    <joint name="fix" type="fixed"><parent link="l3"/><child link="tool0"/><origin xyz="0.05 0.02 0.3" rpy="0.2 -0.1 0.4"/></joint>
    </robot>"""
    path = tmp_path / "toy.urdf"
    path.write_text(urdf)
    model = load_robot(path)
    assert model.dof == 3
    chain = model.pk_chain()
    q = model.sample_joints(100, generator)
    ref = chain.forward_kinematics(q).get_matrix()
    assert (model.flange_pose(q) - ref).abs().max() < 1e-6  # float32 rpy inside pytorch-kinematics


def test_yaml_convention_and_units_are_checked(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nkinematics:\n  convention: dh\n  joints:\n    - {alpha: 0, a: 0, d: 1, theta: 0}\n")
    with pytest.raises(ModelError, match="convention"):
        load_robot(bad)
    bad.write_text("name: x\nkinematics:\n  convention: mdh\n  length_unit: inch\n  joints:\n    - {alpha: 0, a: 0, d: 1, theta: 0}\n")
    with pytest.raises(ModelError, match="length_unit"):
        load_robot(bad)
    bad.write_text("name: x\nkinematics:\n  convention: mdh\n  joints:\n    - {alpha: 0, a: 0, theta: 0}\n")
    with pytest.raises(ModelError, match="lacks"):
        load_robot(bad)


def test_urdf_without_the_named_link(robot, tmp_path):
    path = tmp_path / "r.urdf"
    path.write_text(mdh_to_urdf(robot))
    with pytest.raises(ModelError, match="end_link 'tool0' is not a link"):
        load_robot(path, end_link="tool0")


def test_sample_joints_within_limits(robot, generator):
    q = robot.sample_joints(1000, generator, margin=math.radians(5))
    assert bool(robot.within_limits(q).all())


CONTINUOUS = Path(__file__).parent / "fixtures" / "arm6_continuous.urdf"
OFFSET = Path(__file__).parent / "fixtures" / "arm6_offset.urdf"


def test_continuous_urdf_joint_has_no_limits(generator):
    """A ``type="continuous"`` joint (here with a ``<limit>`` of effort and velocity only, which
    pytorch-kinematics reads as lower = upper = 0) has no limits, and its kinematics are those of the
    same joint declared revolute."""
    robot = load_robot(CONTINUOUS)
    assert robot.continuous.tolist() == [False] * 5 + [True]
    assert robot.joint_limits[5].tolist() == [-math.inf, math.inf]
    assert robot.turn_limits[5].tolist() == [-math.pi, math.pi]
    limited = load_robot(OFFSET)
    torch.testing.assert_close(robot.joint_limits[:5], limited.joint_limits[:5])
    q = robot.sample_joints(500, generator, margin=math.radians(5))
    assert float(q[:, 5].abs().max()) <= math.pi and float(q[:, 5].abs().max()) > 3.0  # one whole turn, no margin
    # any angle is within the limits, and a turn later the flange is where it was
    q[:, 5] += 4 * math.pi
    assert bool(robot.within_limits(q).all()) and not bool(limited.within_limits(q).any())
    torch.testing.assert_close(robot.flange_pose(q), limited.flange_pose(q))


def test_continuous_joint_round_trips_through_yaml_and_urdf(tmp_path):
    robot = load_robot(CONTINUOUS)
    (tmp_path / "r.yaml").write_text(robot_to_yaml(robot))
    assert "continuous: true" in (tmp_path / "r.yaml").read_text()
    (tmp_path / "r.urdf").write_text(mdh_to_urdf(robot))
    assert 'type="continuous"' in (tmp_path / "r.urdf").read_text()
    for back in (load_robot(tmp_path / "r.yaml"), load_robot(tmp_path / "r.urdf")):
        assert back.continuous.tolist() == robot.continuous.tolist()
        torch.testing.assert_close(back.joint_limits[:5], robot.joint_limits[:5])


@pytest.mark.parametrize("row, match", [
    ("continuous: true, min: -90", "continuous and has min/max"),
    ("continuous: 1", "'continuous' must be true or false"),
])
def test_yaml_continuous_flag_is_checked(tmp_path, row, match):
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"name: x\nkinematics:\n  convention: mdh\n  joints:\n    - {{alpha: 0, a: 0, d: 1, theta: 0, {row}}}\n")
    with pytest.raises(ModelError, match=match):
        load_robot(bad)


def test_urdf_parsed_once_and_its_parser_notes_are_one_warning(tmp_path, monkeypatch):
    """A URDF with ROS transmissions (tags the kinematics do not use): the parser's lines become one
    warning naming them, and loading the same text again (the copy a model folder keeps, the links
    named) parses nothing."""
    import warnings

    from pytorch_kinematics.urdf_parser_py.urdf import URDF

    transmissions = "".join(
        f'<transmission name="t{i}"><type>transmission_interface/SimpleTransmission</type>'
        f'<joint name="j{i}"><hardwareInterface>hardware_interface/PositionJointInterface</hardwareInterface></joint>'
        f'<actuator name="m{i}"><hardwareInterface>hardware_interface/PositionJointInterface</hardwareInterface>'
        f'<mechanicalReduction>1</mechanicalReduction></actuator></transmission>' for i in range(1, 7))
    # a comment makes the text unique to this test (the cache is by content)
    text = OFFSET.read_text().replace("</robot>", transmissions + f"<!-- {tmp_path.name} --></robot>")
    first, copy = tmp_path / "ros.urdf", tmp_path / "copy" / "robot.urdf"
    first.write_text(text)
    copy.parent.mkdir()
    copy.write_text(text)
    parses = []
    original = URDF.from_xml_string.__func__
    monkeypatch.setattr(URDF, "from_xml_string", classmethod(lambda cls, xml: parses.append(1) or original(cls, xml)))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        robot = load_robot(first)
        again = load_robot(copy, base_link=robot.base_link, end_link=robot.end_link)
    assert len(parses) == 2  # pytorch-kinematics' chain and the float64 origins, for both loads together
    lines = [str(w.message) for w in caught]
    assert len(lines) == 1 and "skipped 6 element(s)" in lines[0] and 'Unknown tag "hardwareInterface" x6' in lines[0]
    torch.testing.assert_close(again.table, robot.table)
    torch.testing.assert_close(robot.table, load_robot(OFFSET).table)  # the transmissions change nothing


def test_urdf_parser_notes_name_a_misspelt_attribute(tmp_path, capfd):
    text = OFFSET.read_text().replace('<origin xyz="0 0 0.16" rpy="0 0 0"/>', '<origin xyz="0 0 0.16" rpi="0 0 0.1"/>')
    path = tmp_path / "typo.urdf"
    path.write_text(text)
    with pytest.warns(UserWarning, match='Unknown attribute "rpi"'):
        load_robot(path)
    assert "Unknown" not in capfd.readouterr().err  # nothing printed by the parser itself


# ------------------------------------------------------------- typos, duplicates and wrong units

TWIN = Path(__file__).parents[2] / "torchcal" / "resources" / "robots" / "twin-kr6.yaml"
REAL = REAL_DATA  # ../shared/data/real beside the checkout, or TORCHCAL_REAL_DATA


def _twin_with(tmp_path: Path, old: str, new: str) -> Path:
    """The embedded twin's YAML with ``old`` replaced by ``new`` (the edit must apply)."""
    text = TWIN.read_text()
    assert old in text
    path = tmp_path / "robot.yaml"
    path.write_text(text.replace(old, new, 1))
    return path


@pytest.mark.parametrize("old, new, match", [
    ("length_unit: mm", "lenght_unit: mm",
     r"kinematics has unknown key 'lenght_unit' \(did you mean 'length_unit'\?\); allowed: convention, length_unit"),
    ("name: twin-kr6", "name: twin-kr6\nkinematic: {}",
     r"the top level has unknown key 'kinematic' \(did you mean 'kinematics'\?\); allowed: name, kinematics"),
    ("theta: -90,", "thetaa: -90, theta: -90,", r"joint 2 has unknown key 'thetaa' \(did you mean 'theta'\?\)"),
])
def test_unknown_key_at_every_level_is_refused_with_the_closest_match(tmp_path, old, new, match):
    path = _twin_with(tmp_path, old, new)
    with pytest.raises(ModelError, match=match) as info:
        load_robot(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("old, new, match", [
    ("d: 400,", "d: 400, d: 500,", r"line 8: key 'd' is given twice in one mapping"),
    ("angle_unit: deg", "angle_unit: deg\n  length_unit: m", r"line 7: key 'length_unit' is given twice in one "
                                                              r"mapping \(first on line 5\)"),
])
def test_duplicate_yaml_key_is_refused_naming_key_and_line(tmp_path, old, new, match):
    path = _twin_with(tmp_path, old, new)
    with pytest.raises(ModelError, match=match) as info:
        load_robot(path)
    assert str(info.value).startswith(str(path))


def test_yaml_merge_key_may_be_overridden(tmp_path):
    """``<<: *base`` then the same key is YAML's way to override, not a duplicate."""
    path = _twin_with(tmp_path, "    - {alpha: 0,   a: 0,   d: 400, theta: 0,   min: -170, max: 170}",
                      "    - &j1 {alpha: 0,   a: 0,   d: 300, theta: 0,   min: -170, max: 170}\n"
                      "    - {<<: *j1, alpha: -90, a: 25, d: 0, theta: -90, min: -190, max: 45}")
    path.write_text(path.read_text().replace("    - {alpha: -90, a: 25,  d: 0,   theta: -90, min: -190, max: 45}\n", ""))
    robot = load_robot(path)
    assert robot.dof == 6 and robot.table[1, 4] == 0.0 and robot.table[0, 4] == pytest.approx(0.3)


def test_exponent_notation_without_a_dot_is_a_number(robot, tmp_path):
    path = _twin_with(tmp_path, "a: 455,", "a: 455e0,")
    text = path.read_text().replace("d: 420,", "d: 4.2e2,").replace("tool: [0.0, 0.0, 100.0]", "tool: [0, 0, 1E+2]")
    path.write_text(text)
    loaded = load_robot(path)
    assert torch.equal(loaded.table, robot.table) and torch.equal(loaded.tool, robot.tool)
    # a quoted value stays text: refused, naming the key
    path.write_text(text.replace("a: 455e0,", "a: '455e0',"))
    with pytest.raises(ModelError, match="joint 3 'a' must be a number, got '455e0'"):
        load_robot(path)


@pytest.mark.parametrize("old, new, match", [
    ("min: -170, max: 170", "min: -100000, max: 100000",
     r"joint 1 'min'/'max' -100000..100000 deg: beyond \+-20 rad \(1146 deg\): not a joint range"),
    ("angle_unit: deg", "angle_unit: rad", r"joint 1 'min'/'max' -170..170 rad: .*look like degrees: set "
                                           r"kinematics.angle_unit: deg"),
    ("min: -350, max: 350", "min: 1200, max: 1300", r"joint 6 'min'/'max' 1200..1300 deg: beyond \+-20 rad"),
])
def test_yaml_joint_limits_beyond_any_joint_travel_are_refused(tmp_path, old, new, match):
    with pytest.raises(ModelError, match=match):
        load_robot(_twin_with(tmp_path, old, new))


@pytest.mark.parametrize("limits, high_deg", [
    ("min: -360, max: 360", 360.0),  # as a UR's joints
    ("min: -400, max: 400", 400.0),  # ABB axis 6
    ("min: -450, max: 450", 450.0),  # FANUC J6
])
def test_real_wrist_travels_are_accepted(tmp_path, limits, high_deg):
    robot = load_robot(_twin_with(tmp_path, "min: -350, max: 350", limits))
    assert float(robot.joint_limits[5, 1]) == pytest.approx(math.radians(high_deg))
    # a generated UR URDF writes its +-2 pi a hair over: still a joint range
    from torchcal.kinematics.robot_checks import joint_span_problem

    assert not joint_span_problem(-6.28318530718, 6.28318530718)


def _offset_urdf_with(tmp_path: Path, edit) -> Path:
    path = tmp_path / "arm.urdf"
    path.write_text(edit(OFFSET.read_text()) + f"<!-- {tmp_path.name} -->")  # unique text: the cache is by content
    return path


def test_urdf_limits_in_degrees_are_refused(tmp_path):
    path = _offset_urdf_with(tmp_path, lambda t: t.replace('lower="-3.0" upper="3.0"', 'lower="-170" upper="170"', 1))
    with pytest.raises(ModelError, match=r"joint 'j1': <limit lower/upper> -170, 170 rad: beyond \+-20 rad "
                                         r"\(1146 deg\): they look like degrees where URDF expects radians"):
        load_robot(path)


def test_urdf_in_millimetres_is_refused(tmp_path):
    import re

    def to_mm(text: str) -> str:
        scale = lambda m: 'xyz="' + " ".join(f"{float(v) * 1000:g}" for v in m.group(1).split()) + '"'  # noqa: E731
        return re.sub(r'(?<=<origin )xyz="([^"]*)"', scale, text)

    path = _offset_urdf_with(tmp_path, to_mm)
    assert load_robot(OFFSET).table[:, 1].abs().max() > 0.1  # the edit scaled real lengths
    with pytest.raises(ModelError, match=r"arm.urdf: the nominal TCP reaches [0-9.e+]+ m from the base, beyond what "
                                         r"an arm reaches \(0.05 to 20 m\): the lengths look like millimetres"):
        load_robot(path)


@pytest.mark.parametrize("unit, scale, expected", [("m", 1.0, "mm"), ("mm", 1e-3, "m")])
def test_yaml_length_unit_that_does_not_match_its_values_is_refused(tmp_path, unit, scale, expected):
    """The twin (mm) declared in metres, and the twin written in metres declared in mm."""
    import re

    path = _twin_with(tmp_path, "length_unit: mm", f"length_unit: {unit}")
    text = re.sub(r"\b(a|d): +(-?[0-9.]+)", lambda m: f"{m.group(1)}: {float(m.group(2)) * scale:g}", path.read_text())
    path.write_text(text.replace("tool: [0.0, 0.0, 100.0]", f"tool: [0, 0, {100 * scale:g}]"))
    assert scale == 1.0 or "d: 0.4," in path.read_text()
    with pytest.raises(ModelError, match=rf"robot.yaml: the nominal TCP reaches .* kinematics.length_unit is '{unit}' "
                                         rf"but the values \(a, d, tool\) look like {expected}: set length_unit: "
                                         rf"{expected}"):
        load_robot(path)


def test_negative_d1_is_legal_geometry(tmp_path):
    loaded = load_robot(_twin_with(tmp_path, "d: 400,", "d: -400,"))
    assert float(loaded.table[0, 4]) == pytest.approx(-0.4)


@pytest.mark.parametrize("path", sorted((Path(__file__).parents[2] / "torchcal" / "resources" / "robots").glob("*.yaml"))
                         + sorted(REAL.glob("*/robot.yaml")), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_embedded_and_real_robot_files_load(path):
    robot = load_robot(path)
    assert robot.dof >= 6


@pytest.mark.real
def test_real_robot_folder_has_robot_files():
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is not here")
    assert list(REAL.glob("*/robot.yaml"))
