"""Analytic parameter Jacobian vs reverse-mode autodiff vs central finite differences."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from helpers import central_difference

from torchcal.core.errors import ModelError
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.param_jacobian import so3_right_jacobian, tcp_position_jacobian
from torchcal.kinematics.robot import RobotModel, default_robot_path, load_robot

FIXTURES = Path(__file__).resolve().parent / "fixtures"



def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm())


def _seven_joint_robot() -> RobotModel:
    """A 7R arm (Craig MDH of a common collaborative arm), with a tool on the flange."""
    deg = math.pi / 180
    rows = [  # alpha, a, beta, theta, d
        [0.0, 0.0, 0.0, 0.0, 0.333],
        [-90 * deg, 0.0, 0.0, 0.0, 0.0],
        [90 * deg, 0.0, 0.0, 0.0, 0.316],
        [90 * deg, 0.0825, 0.0, 0.0, 0.0],
        [-90 * deg, -0.0825, 0.0, 0.0, 0.384],
        [90 * deg, 0.0, 0.0, 0.0, 0.0],
        [90 * deg, 0.088, 0.0, 0.0, 0.107],
    ]
    limits = [[-2.8, 2.8], [-1.7, 1.7], [-2.8, 2.8], [-3.0, -0.1], [-2.8, 2.8], [0.0, 3.7], [-2.8, 2.8]]
    return RobotModel(
        name="arm7",
        joint_names=tuple(f"joint{i}" for i in range(1, 8)),
        table=torch.tensor(rows, dtype=torch.float64),
        joint_limits=torch.tensor(limits, dtype=torch.float64),
        tool=torch.tensor([0.01, -0.02, 0.15], dtype=torch.float64),
    )


def _robots() -> dict[str, RobotModel]:
    return {
        "twin": load_robot(default_robot_path()),
        "arm7": _seven_joint_robot(),
        "urdf": load_robot(FIXTURES / "arm6_offset.urdf", tool=(0.01, 0.02, 0.12)),
    }


ROBOTS = _robots()


def _case(robot: RobotModel, seed: int) -> tuple[ErrorModel, torch.Tensor, torch.Tensor]:
    """A model with a rotated, shifted instrument frame and a random perturbed parameter vector.

    Every parameter is perturbed, fixed ones included: the Jacobian must be right for all columns
    (beta on every joint, a large base rotation vector, a tool orientation).
    """
    gen = torch.Generator().manual_seed(seed)
    reference = tf.homogeneous(tf.so3_exp(torch.tensor([0.4, -1.1, 0.7], dtype=torch.float64)), torch.tensor([2.0, -0.5, 0.8], dtype=torch.float64))
    model = ErrorModel(robot, T_instrument_base=reference)
    x = model.nominal_vector()
    is_angle = model.layout.is_angle()
    x = x + torch.randn(x.shape, generator=gen, dtype=torch.float64) * torch.where(is_angle, 0.02, 0.005)
    x[model.layout.base_slice] = torch.tensor([0.03, -0.02, 0.05, 0.3, -0.5, 0.4], dtype=torch.float64)
    q = robot.sample_joints(24, gen)
    return model, q, x


@pytest.mark.parametrize("name", list(ROBOTS))
def test_analytic_jacobian_matches_autodiff_and_finite_differences(name):
    robot = ROBOTS[name]
    model, q, x = _case(robot, seed=3)
    assert float(x[model.layout.index("beta2")].abs()) > 0  # non-zero Hayati tilt everywhere
    if name == "urdf":
        assert (robot.T_base_0 - torch.eye(4, dtype=torch.float64)).abs().max() > 0.1
        assert (robot.T_n_flange - torch.eye(4, dtype=torch.float64)).abs().max() > 0.1
    p_an, jac_an = model.position_jacobian_analytic(q, x)
    p_ad, jac_ad = model.position_jacobian(q, x)
    fd = central_difference(lambda v: model.tcp_position(q, v), x)
    assert jac_an.shape == (24, 3, model.layout.size) and jac_an.is_contiguous()
    assert (p_an - p_ad).abs().max() < 1e-12
    assert (p_an - model.tcp_pose(q, x)[:, :3, 3]).abs().max() < 1e-12
    assert _rel(jac_an, jac_ad) <= 1e-6
    assert _rel(jac_an, fd) <= 1e-6
    assert _rel(jac_ad, fd) <= 1e-6
    # every block separately, so that a small block cannot hide in the norm of the large ones
    lay = model.layout
    for block in (lay.table_slice, lay.base_slice, slice(lay.tool_slice.start, lay.tool_slice.start + 3)):
        assert _rel(jac_an[..., block], fd[..., block]) <= 1e-6
    assert jac_an[..., lay.tool_slice.start + 3 :].abs().max() == 0.0  # a point has no orientation


def test_columns_masks_batch_dims_and_chunks_agree():
    model, q, x = _case(ROBOTS["twin"], seed=4)
    _, full = model.position_jacobian_analytic(q, x)
    active = model.default_active()
    cols = active.nonzero().squeeze(-1)
    p, jac = model.position_jacobian(q, x, cols, method="analytic")
    assert (jac - full[..., cols]).abs().max() == 0.0
    _, by_mask = tcp_position_jacobian(model, q, x, active)
    assert torch.equal(by_mask, jac)
    _, ad = model.position_jacobian(q, x, cols)
    assert _rel(jac, ad) <= 1e-6
    # chunking is a memory detail: identical numbers; leading batch dims are kept
    p_small, jac_small = tcp_position_jacobian(model, q, x, cols, chunk=5)
    assert torch.equal(p_small, p) and torch.equal(jac_small, jac)
    p_2d, jac_2d = tcp_position_jacobian(model, q.reshape(4, 6, -1), x, cols)
    assert jac_2d.shape == (4, 6, 3, cols.numel()) and torch.equal(jac_2d.reshape(jac.shape), jac)
    assert torch.equal(p_2d.reshape(p.shape), p)


def test_analytic_jacobian_rejects_bad_input():
    model, q, x = _case(ROBOTS["twin"], seed=5)
    with pytest.raises(ModelError, match="shared parameter vector"):
        model.position_jacobian_analytic(q, x.expand(q.shape[0], -1))
    with pytest.raises(ModelError, match="joints"):
        model.position_jacobian_analytic(q[:, :5], x)
    with pytest.raises(ModelError, match="outside"):
        model.position_jacobian_analytic(q, x, torch.tensor([0, 99]))
    with pytest.raises(ModelError, match="method"):
        model.position_jacobian(q, x, method="numeric")


def test_so3_right_jacobian_against_finite_differences():
    for r in (torch.tensor([0.3, -0.5, 0.4]), torch.tensor([1e-6, 2e-6, -1e-6]), torch.tensor([2.0, 0.5, -1.0])):
        r = r.to(torch.float64)
        jr = so3_right_jacobian(r)
        # exp(r + dr) = exp(r) exp(J_r dr): the rotation vector of exp(r)^T exp(r + dr) per dr
        fd = central_difference(lambda v: tf.so3_log(tf.so3_exp(r).T @ tf.so3_exp(v)), r, eps=1e-6)
        assert (jr - fd).abs().max() < 1e-8


def test_link_parameter_gradients_reach_every_table_entry():
    """Autodiff through the error layer reaches every MDH entry (the analytical-grad FK of
    pytorch-kinematics 0.10 treats link offsets as constants and returns no gradient for them)."""
    robot = ROBOTS["urdf"]
    model, q, x = _case(robot, seed=6)
    weights = torch.randn(q.shape[0], 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def loss(v: torch.Tensor) -> torch.Tensor:
        return (model.tcp_position(q, v) * weights).sum().reshape(1)

    xg = x.clone().requires_grad_(True)
    loss(xg).backward()
    grad = xg.grad[model.layout.table_slice]
    fd = central_difference(loss, x)[0, model.layout.table_slice]
    assert (grad - fd).abs().max() <= 1e-6 * fd.abs().max()
    assert bool((grad.abs() > 1e-6).all())  # no entry is silently cut off
