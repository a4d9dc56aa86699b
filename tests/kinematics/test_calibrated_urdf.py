"""The calibrated URDF predicts the calibrated geometry, read by pytorch-kinematics and by a parser of its own.

Truth: the error model's chain (:meth:`ErrorModel.base_flange_pose` and the tool) for a perturbed
parameter vector; the URDF must reproduce it to 1e-9 m (1e-6 mm) at random joint angles, and keep
every element of the user's file other than the moving joints' origins.
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import pytorch_kinematics as pk
import pytorch_kinematics.transforms as pkt
import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics.calibrated_urdf import MOVING, calibrated_urdf, rpy_of
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import default_robot_path, load_robot
from torchcal.kinematics.transforms import euler_xyz_to_matrix

FIXTURE = Path(__file__).parent / "fixtures" / "arm6_offset.urdf"
TOLERANCE_M = 1e-9  # 1e-6 mm


# ----------------------------------------------------------------- an independent URDF reader (numpy)


def _rpy_matrix(r: float, p: float, y: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def numpy_fk(text: str, base: str, tip: str, q: np.ndarray) -> np.ndarray:
    """Position of link ``tip`` in link ``base`` for joints ``q`` (moving joints in chain order)."""
    root = ET.fromstring(text)
    by_child = {j.find("child").get("link"): j for j in root.iter("joint")}
    chain, link = [], tip
    while link != base:
        chain.append(by_child[link])
        link = by_child[link].find("parent").get("link")
    out = []
    for qs in q:
        T, k = np.eye(4), 0
        for joint in reversed(chain):
            origin = joint.find("origin")
            step = np.eye(4)
            if origin is not None:
                step[:3, :3] = _rpy_matrix(*[float(v) for v in origin.get("rpy", "0 0 0").split()])
                step[:3, 3] = [float(v) for v in origin.get("xyz", "0 0 0").split()]
            T = T @ step
            if joint.get("type") in MOVING:
                axis_el = joint.find("axis")
                axis = np.array([float(v) for v in axis_el.get("xyz").split()]) if axis_el is not None else np.array([1.0, 0, 0])
                rot = np.eye(4)
                rot[:3, :3] = _axis_angle(axis, qs[k])
                T, k = T @ rot, k + 1
        out.append(T[:3, 3])
    return np.array(out)


def pk_fk(text: str, base: str, tip: str, q: torch.Tensor, float64_origins: bool) -> torch.Tensor:
    """pytorch-kinematics' FK; with ``float64_origins`` its URDF reader's float32 ``rpy``/``xyz`` are
    replaced by float64 ones built with its own ``quaternion_from_euler`` (the library rounds them)."""
    original, defaults = pk.urdf._convert_transform, pk.chain.Chain.__init__.__defaults__

    def convert64(origin):
        if origin is None:
            return pkt.Transform3d(dtype=torch.float64)
        rpy = torch.tensor(origin.rpy, dtype=torch.float64)
        return pkt.Transform3d(rot=pkt.quaternion_from_euler(rpy, "sxyz"), pos=torch.tensor(origin.xyz, dtype=torch.float64),
                               dtype=torch.float64)

    if float64_origins:  # its reader converts every origin, and builds every chain, in float32
        pk.urdf._convert_transform = convert64
        pk.chain.Chain.__init__.__defaults__ = (torch.float64, "cpu")
    try:
        chain = pk.build_serial_chain_from_urdf(text.encode(), tip, base).to(dtype=torch.float64)
    finally:
        pk.urdf._convert_transform = original
        pk.chain.Chain.__init__.__defaults__ = defaults
    return chain.forward_kinematics(q).get_matrix()[:, :3, 3]


# ---------------------------------------------------------------------------------------- cases


def _perturbed(robot, seed: int, with_orientation: bool = True):
    """An error model and a parameter vector a few mm / mrad away from nominal on every row and the tool."""
    model = ErrorModel(robot, with_orientation=with_orientation)
    g = torch.Generator().manual_seed(seed)
    x = model.nominal_vector()
    table = model.layout.table_slice
    x[table] += 2e-3 * torch.randn(x[table].shape, generator=g, dtype=torch.float64)
    tool = model.layout.tool_slice
    x[tool] += torch.tensor([0.012, -0.034, 0.151, 0.05, -0.02, 0.3], dtype=torch.float64)
    return model, x


def _truth(model: ErrorModel, x: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    return (model.base_flange_pose(q, x) @ model.flange_from_tool(x))[..., :3, 3]


@pytest.fixture(scope="module", params=["urdf", "mdh"])
def case(request):
    robot = load_robot(FIXTURE, tool=(0.0, 0.0, 0.05)) if request.param == "urdf" else load_robot(default_robot_path())
    model, x = _perturbed(robot, seed=7)
    text, tcp = calibrated_urdf(robot, model.table(x), model.flange_from_tool(x), ["a note -- with dashes"])
    q = robot.sample_joints(200, torch.Generator().manual_seed(3))
    return robot, model, x, text, tcp, q


def test_independent_parser_predicts_the_calibrated_points(case):
    robot, model, x, text, tcp, q = case
    got = numpy_fk(text, robot.base_link, tcp, q.numpy())
    err = np.abs(got - _truth(model, x, q).numpy()).max()
    assert err < TOLERANCE_M
    # and the calibration moved the points by far more than that: the check can fail
    nominal = numpy_fk(calibrated_urdf(robot, robot.table, model.flange_from_tool(model.nominal_vector()), [])[0],
                       robot.base_link, tcp, q.numpy())
    assert np.abs(nominal - got).max() > 1e-3


def test_pytorch_kinematics_predicts_the_calibrated_points(case):
    robot, model, x, text, tcp, q = case
    truth = _truth(model, x, q)
    exact = pk_fk(text, robot.base_link, tcp, q, float64_origins=True)
    assert float((exact - truth).abs().max()) < TOLERANCE_M
    # the stock reader rounds origins to float32: still within a micrometre
    stock = pk_fk(text, robot.base_link, tcp, q, float64_origins=False)
    assert float((stock - truth).abs().max()) < 1e-6


def test_only_moving_joint_origins_change():
    robot = load_robot(FIXTURE, tool=(0.0, 0.0, 0.05))
    model, x = _perturbed(robot, seed=9)
    text, tcp = calibrated_urdf(robot, model.table(x), model.flange_from_tool(x), ["note"])
    before, after = ET.fromstring(FIXTURE.read_text()), ET.fromstring(text)
    added = {e.get("name") for e in after if e.tag in ("link", "joint")} - {e.get("name") for e in before}
    assert added == {tcp, f"{tcp}_joint"}
    changed = 0
    for old in before:
        new = after.find(f"{old.tag}[@name='{old.get('name')}']")
        assert new is not None
        a, b = copy.deepcopy(old), copy.deepcopy(new)
        for element in (a, b):
            if element.tag == "joint" and element.get("type") in MOVING:
                origin = element.find("origin")
                if origin is not None:
                    element.remove(origin)
                    changed += 1
            for e in element.iter():
                e.tail = e.text = None
        assert ET.tostring(a) == ET.tostring(b), old.get("name")
    assert changed == 2 * robot.dof


def test_comment_lists_what_it_cannot_hold(case):
    *_, text, _tcp, _q = case
    root = ET.fromstring(text, parser=ET.XMLParser(target=ET.TreeBuilder(insert_comments=True)))
    comments = [e.text for e in root if e.tag is ET.Comment]
    assert comments and "a note - - with dashes" in comments[0]


def test_rpy_round_trips_at_gimbal_lock():
    for angles in ([0.3, np.pi / 2, -0.2], [0.1, -np.pi / 2 + 1e-9, 1.0], [2.0, 0.4, -3.0]):
        rot = euler_xyz_to_matrix(torch.tensor(angles, dtype=torch.float64))
        back = euler_xyz_to_matrix(torch.tensor(rpy_of(rot), dtype=torch.float64))
        assert torch.allclose(back, rot, atol=1e-14)


def test_a_urdf_whose_joint_count_differs_is_refused():
    robot = load_robot(FIXTURE, tool=(0.0, 0.0, 0.05))
    model, x = _perturbed(robot, seed=1)
    broken = robot.urdf.replace('name="j3" type="revolute"', 'name="j3" type="fixed"')
    with pytest.raises(ModelError, match="moving joints"):
        calibrated_urdf(type(robot)(**{**robot.__dict__, "urdf": broken}), model.table(x), model.flange_from_tool(x), [])
