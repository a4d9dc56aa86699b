"""Fast MDH+beta chain kernels against the plain product of 4x4 link transforms."""

from __future__ import annotations

import math

import pytest
import torch

from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.mdh import chain_frames, chain_point, chain_transforms, link_transform
from torchcal.kinematics.robot import default_robot_path, load_robot


def _reference_frames(q: torch.Tensor, table: torch.Tensor) -> list[torch.Tensor]:
    """Every ``T_0_i`` as a product of homogeneous link transforms (the textbook definition)."""
    alpha, a, beta, theta0, d = table.unbind(-1)
    rot, trans = link_transform(alpha, a, beta, theta0 + q, d)
    frames, acc = [], None
    for i in range(q.shape[-1]):
        link = tf.homogeneous(rot[..., i, :, :], trans[..., i, :])
        acc = link if acc is None else acc @ link
        frames.append(acc)
    return frames


@pytest.fixture(scope="module")
def twin():
    return load_robot(default_robot_path())


def _tilted_table(robot, generator) -> torch.Tensor:
    table = robot.table.clone()
    table += 0.01 * torch.randn(table.shape, generator=generator, dtype=torch.float64)
    return table


def test_chain_transforms_matches_link_products(twin):
    gen = torch.Generator().manual_seed(7)
    table = _tilted_table(twin, gen)
    q = twin.sample_joints(64, gen)
    ref = _reference_frames(q, table)
    rot, pos = chain_transforms(q, table)
    assert rot.shape == (64, 3, 3) and pos.shape == (64, 3)
    assert (rot - ref[-1][:, :3, :3]).abs().max() < 1e-12
    assert (pos - ref[-1][:, :3, 3]).abs().max() < 1e-12
    rot_all, pos_all = chain_transforms(q, table, all_frames=True)
    assert rot_all.shape == (64, 6, 3, 3) and pos_all.shape == (64, 6, 3)
    for i, frame in enumerate(ref):
        assert (rot_all[:, i] - frame[:, :3, :3]).abs().max() < 1e-12
        assert (pos_all[:, i] - frame[:, :3, 3]).abs().max() < 1e-12


def test_chain_kernels_broadcast_per_pose_tables_and_single_poses(twin):
    gen = torch.Generator().manual_seed(8)
    q = twin.sample_joints(12, gen).reshape(3, 4, 6)
    tables = twin.table + 0.02 * torch.randn(3, 4, 6, 5, generator=gen, dtype=torch.float64)
    ref = _reference_frames(q, tables)[-1]
    rot, pos = chain_transforms(q, tables)
    assert rot.shape == (3, 4, 3, 3)
    assert (rot - ref[..., :3, :3]).abs().max() < 1e-12 and (pos - ref[..., :3, 3]).abs().max() < 1e-12
    point = torch.tensor([0.01, -0.02, 0.1], dtype=torch.float64)
    expected = (ref[..., :3, :3] @ point) + ref[..., :3, 3]
    assert (chain_point(q, tables, point) - expected).abs().max() < 1e-12
    # one pose, shared table
    rot1, _pos1 = chain_transforms(q[0, 0], twin.table)
    ref1 = _reference_frames(q[0, 0], twin.table)[-1]
    assert rot1.shape == (3, 3) and (rot1 - ref1[:3, :3]).abs().max() < 1e-12
    assert chain_point(q[0, 0], twin.table, point).shape == (3,)


def test_chain_frames_start_frame_and_intermediate_axes(twin):
    gen = torch.Generator().manual_seed(9)
    table = _tilted_table(twin, gen)
    q = twin.sample_joints(16, gen)
    start = tf.homogeneous(tf.so3_exp(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)), torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64))
    frames = chain_frames(q, table, r_start=start[:3, :3], p_start=start[:3, 3])
    ref = [start @ f for f in _reference_frames(q, table)]
    for i, frame in enumerate(ref):
        assert (frames.stacked("z")[:, i] - frame[:, :3, 2]).abs().max() < 1e-12
        assert (frames.stacked("o")[:, i] - frame[:, :3, 3]).abs().max() < 1e-12
        prev = start if i == 0 else ref[i - 1]
        alpha, a = table[i, 0], table[i, 1]
        # the beta axis is y after Rx(alpha); its point is o_{i-1} + a x_{i-1}
        y_mid = prev[..., :3, :3] @ tf.rot_x(alpha)[:, 1]
        m_mid = prev[..., :3, 3] + a * prev[..., :3, 0]
        assert (frames.stacked("y_mid")[:, i] - y_mid).abs().max() < 1e-12
        assert (frames.stacked("m_mid")[:, i] - m_mid).abs().max() < 1e-12
    point = torch.tensor([0.0, 0.05, 0.1], dtype=torch.float64)
    expected = ref[-1][:, :3, :3] @ point + ref[-1][:, :3, 3]
    got = chain_point(q, table, point, r_start=start[:3, :3], p_start=start[:3, 3])
    assert (got - expected).abs().max() < 1e-12


def test_tcp_position_matches_full_pose_product(twin):
    """The fast TCP path equals T_instrument_base T_base_0 T_0_N T_N_flange T_flange_tool."""
    gen = torch.Generator().manual_seed(10)
    model = ErrorModel(twin, T_instrument_base=tf.homogeneous(tf.rot_z(torch.tensor(0.7, dtype=torch.float64)), torch.tensor([1.5, -0.3, 0.2], dtype=torch.float64)))
    x = model.nominal_vector()
    x[model.layout.table_slice] += 1e-3 * torch.randn(30, generator=gen, dtype=torch.float64)
    x[model.layout.base_slice] = torch.tensor([0.01, -0.02, 0.03, 0.1, -0.2, 0.3], dtype=torch.float64)
    q = twin.sample_joints(40, gen)
    ref = model.instrument_from_base(x) @ model.T_base_0 @ _reference_frames(q, model.table(x))[-1] @ model.T_n_flange
    expected = ref[:, :3, :3] @ x[model.layout.tool_slice][:3] + ref[:, :3, 3]
    assert (model.tcp_position(q, x) - expected).abs().max() < 1e-12
    # per-pose parameter vectors (the autodiff Jacobian's route)
    xs = x + 1e-3 * torch.randn(40, x.shape[0], generator=gen, dtype=torch.float64)
    ref = model.instrument_from_base(xs) @ model.T_base_0 @ _reference_frames(q, model.table(xs))[-1] @ model.T_n_flange
    expected = (ref[:, :3, :3] @ xs[:, model.layout.tool_slice][:, :3, None]).squeeze(-1) + ref[:, :3, 3]
    assert (model.tcp_position(q, xs) - expected).abs().max() < 1e-12


def test_gradients_through_fast_kernels_match_reference(twin):
    gen = torch.Generator().manual_seed(11)
    table = _tilted_table(twin, gen).requires_grad_(True)
    q = twin.sample_joints(10, gen).requires_grad_(True)
    point = torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64)
    weights = torch.randn(10, 3, generator=gen, dtype=torch.float64)
    g_fast = torch.autograd.grad((chain_point(q, table, point) * weights).sum(), (q, table))
    ref = _reference_frames(q, table)[-1]
    g_ref = torch.autograd.grad(((ref[:, :3, :3] @ point + ref[:, :3, 3]) * weights).sum(), (q, table))
    for fast, slow in zip(g_fast, g_ref):
        assert (fast - slow).abs().max() < 1e-12
    assert math.isfinite(float(g_fast[1].abs().sum())) and float(g_fast[1].abs().sum()) > 0.1
