"""The stiffness stage of the graphs against the VJM of torchcal.stiffness (torch side only)."""


import pytest
import torch
from known_cases import KnownResidual, nominal_tcp_pose, residual_value

from torchcal.compensate.chain import ChainGraph
from torchcal.compensate.compensator import (
    CompensatorGraph,
    LoadedCompensatorGraph,
    LoadedMonitorGraph,
    MonitorGraph,
)
from torchcal.compensate.deflection import DeflectionGraph
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.stages.store import load_model
from torchcal.stiffness.vjm import classic_compliance, deflection


@pytest.fixture(scope="module")
def stored(model_dir):
    return load_model(model_dir)


@pytest.fixture(scope="module")
def base_model(stored):
    """The calibrated model with an identity instrument frame: its outputs are in ``base``."""
    x = stored.x.clone()
    x[stored.model.layout.base_slice] = 0.0
    return ErrorModel(stored.robot), x


def full_compliance(n: int, seed: int) -> torch.Tensor:
    """A random symmetric positive definite 6x6 compliance per joint, KR6-like magnitudes."""
    gen = torch.Generator().manual_seed(seed)
    a = torch.randn(n, 6, 6, generator=gen, dtype=torch.float64)
    scale = torch.tensor([1e-8] * 3 + [1e-5] * 3, dtype=torch.float64)
    return (a @ a.transpose(-1, -2) / 6 + torch.eye(6, dtype=torch.float64)) * torch.outer(scale, scale).sqrt()


def wrenches(n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(n, 6, generator=gen, dtype=torch.float64) * torch.tensor([150.0] * 3 + [15.0] * 3, dtype=torch.float64)


def chain_outputs(model, x, q):
    tables = model.table(x).unsqueeze(0)
    end = (model.T_n_flange @ model.flange_from_tool(x)).unsqueeze(0)
    pose, frames = ChainGraph(tables, model.T_base_0, end)(q, with_frames=True)
    return pose[:, 0], frames[:, 0]


@pytest.mark.parametrize("frame, vjm_frame", [("tool", "tool"), ("base", "instrument")])
def test_deflection_graph_matches_vjm(stored, base_model, frame, vjm_frame):
    model, x = base_model
    q = stored.robot.sample_joints(500, torch.Generator().manual_seed(41))
    c, w = full_compliance(stored.robot.dof, 42), wrenches(500, 43)
    pose, frames = chain_outputs(model, x, q)
    dp, dphi = DeflectionGraph(c, wrench_frame=frame)(pose, frames, w)
    ref = deflection(model, q, x, c, w, wrench_frame=vjm_frame)
    assert float(ref[:, :3].norm(dim=-1).median()) > 1e-4  # a real deflection, not zeros
    assert (dp - ref[:, :3]).abs().max() <= 1e-12 * ref[:, :3].abs().max()
    assert (dphi - ref[:, 3:]).abs().max() <= 1e-12 * ref[:, 3:].abs().max()


def test_loaded_rotation_is_the_exponential_to_third_order(stored, base_model):
    model, x = base_model
    q = stored.robot.sample_joints(200, torch.Generator().manual_seed(44))
    graph = DeflectionGraph(full_compliance(stored.robot.dof, 45))
    pose, frames = chain_outputs(model, x, q)
    w = wrenches(200, 46)
    _, dphi = graph(pose, frames, w)
    _, rotation = graph.loaded_pose(pose, frames, w)
    exact = tf.so3_exp(dphi) @ pose[:, :3, :3]
    angle = dphi.norm(dim=-1)
    assert float(angle.max()) > 1e-3
    assert bool(((rotation - exact).abs().amax((-1, -2)) <= angle**3 / 6 + 1e-15).all())


def regular(stored, q, min_singular=0.05):
    _, jac = geometric_jacobian(ErrorModel(stored.robot), q, stored.x)
    return torch.linalg.svdvals(jac)[:, -1] > min_singular


def test_loaded_compensator_puts_the_loaded_tcp_on_target(stored, base_model):
    """At q_c: calibrated pose + residual + VJM deflection (computed independently) = nominal target."""
    model, x = base_model
    c = classic_compliance(torch.tensor([3e5, 2e5, 2.5e5, 2e4, 3e4, 2e4], dtype=torch.float64))
    q = stored.robot.sample_joints(800, torch.Generator().manual_seed(47))
    q = q[regular(stored, q)][:300]
    w = wrenches(len(q), 48)
    graph = LoadedCompensatorGraph(stored.model, stored.x, c, KnownResidual())
    with torch.no_grad():
        q_c = graph(q, w)
    target = nominal_tcp_pose(stored.robot, q)
    pose = model.tcp_pose(q_c, x)
    d = deflection(model, q_c, x, c, w)
    p = pose[:, :3, 3] + residual_value(q_c) + d[:, :3]
    rot = tf.so3_exp(d[:, 3:]) @ pose[:, :3, :3]
    before = (model.tcp_pose(q, x)[:, :3, 3] + residual_value(q) + deflection(model, q, x, c, w)[:, :3] - target[:, :3, 3]).norm(dim=-1)
    assert float(before.median()) > 1e-4
    # the rigid Jacobian of the Newton steps leaves ~1e-3 of the deflection's change per step
    left = (p - target[:, :3, 3]).norm(dim=-1)
    assert float(left.median()) < 1e-10 and float(left.max()) < 1e-8
    # rotation: plus the graph's second-order exponential (|dphi|^3 / 6, dphi up to ~5e-3 rad here)
    assert float(tf.so3_log(rot @ target[:, :3, :3].transpose(-1, -2)).norm(dim=-1).max()) < 1e-7


def test_zero_wrench_is_the_unloaded_compensator(stored):
    c = classic_compliance(torch.tensor([3e5, 2e5, 2.5e5, 2e4, 3e4, 2e4], dtype=torch.float64))
    q = stored.robot.sample_joints(300, torch.Generator().manual_seed(49))
    zero = torch.zeros(300, 6, dtype=torch.float64)
    with torch.no_grad():
        loaded = LoadedCompensatorGraph(stored.model, stored.x, c)(q, zero)
        plain = CompensatorGraph(stored.model, stored.x)(q)
        loaded_mon = LoadedMonitorGraph(stored.model, stored.x, c)(q, zero)
        plain_mon = MonitorGraph(stored.model, stored.x)(q)
    assert (loaded - plain).abs().max() < 1e-12
    assert (loaded_mon - plain_mon).abs().max() < 1e-12


def test_loaded_monitor_adds_the_deflection(stored, base_model):
    model, x = base_model
    c = full_compliance(stored.robot.dof, 50)
    q = stored.robot.sample_joints(300, torch.Generator().manual_seed(51))
    w = wrenches(300, 52)
    with torch.no_grad():
        out = LoadedMonitorGraph(stored.model, stored.x, c, KnownResidual())(q, w)
    ref = model.tcp_pose(q, x)[:, :3, 3] + residual_value(q) + deflection(model, q, x, c, w)[:, :3] - stored.robot.tcp_position(q)
    assert (out - ref).norm(dim=-1).max() < 1e-12


def test_wrench_frame_is_checked():
    with pytest.raises(ValueError, match="wrench_frame"):
        DeflectionGraph(torch.zeros(6, 6, 6), wrench_frame="instrument")
