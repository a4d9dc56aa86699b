"""Deformed kinematics: the chain with its virtual springs deflected, and its re-derived table.

A spring deformation ``theta_i = [t; r]`` (m, rad, in joint frame ``i``) moves everything after
joint ``i`` by ``D_i = [exp([r]x), t]`` applied on the right of joint frame ``i``::

    T_instrument_tool = T_instrument_base T_base_0 prod_i (A_i(q_i) D_i) T_N_flange T_flange_tool

The derivative of this chain at ``theta = 0`` is the VJM Jacobian of :mod:`torchcal.stiffness.vjm`.

For a *fixed* deformation the chain is again a serial chain of revolute joints with fixed links
between their axes, so it has an MDH(+beta) description of its own: :func:`rederive_parameters`
finds it with the axis method (:func:`torchcal.kinematics.axes.mdh_from_axes`) from the deformed
joint axes at the zero configuration.

Hayati threshold. The axis method treats consecutive axes closer than
``parallel_threshold_rad`` to parallel with Hayati's ``beta`` (origin kept where the previous
normal arrives, the tilt in ``beta``) instead of the common normal. Spring deformations tilt a
nominally parallel pair (axes 2 and 3 of a 6R arm) by 1e-4 to 1e-2 rad; if the threshold were
below that tilt, the pair would switch to the common-normal convention and its ``d`` would jump
to about ``a / tilt`` (metres). The default here is therefore the error layer's 2 deg
(:data:`DEFAULT_PARALLEL_THRESHOLD_RAD`), far above any elastic tilt and far below the angle
between genuinely skew axes (90 deg on industrial arms), rather than the axis method's
geometric default of 1e-3 rad.
"""

from __future__ import annotations

import math

import torch

from torchcal.kinematics import transforms as tf
from torchcal.kinematics.axes import AxisFrames, mdh_from_axes
from torchcal.kinematics.error_model import DEFAULT_PARALLEL_THRESHOLD_DEG, ErrorModel
from torchcal.kinematics.mdh import link_transform
from torchcal.stiffness.vjm import (
    WrenchFrame,
    spring_deformations,
    twist_blocks,
    wrench_in_instrument,
)

DEFAULT_PARALLEL_THRESHOLD_RAD = math.radians(DEFAULT_PARALLEL_THRESHOLD_DEG)
"""Hayati switch for re-derived tables (2 deg, see the module docstring)."""


def spring_transform(theta: torch.Tensor) -> torch.Tensor:
    """``D = [exp([r]x), t]`` ``(..., 4, 4)`` of spring deformations ``theta = [t; r]`` ``(..., 6)``."""
    return tf.homogeneous(tf.so3_exp(theta[..., 3:]), theta[..., :3])


def deformed_joint_poses(
    model: ErrorModel, q: torch.Tensor, x: torch.Tensor, theta: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Deformed joint frames and flange of the chain.

    Args:
        q: ``(..., N)`` joints, rad.
        x: ``(P,)`` or ``(..., P)`` error-layer parameters.
        theta: ``(..., N, 6)`` spring deformations (m, rad) in each joint frame.

    Returns:
        ``(frames, flange)``: ``T_instrument_joint_i`` *after* its spring ``(..., N, 4, 4)`` and
        ``T_instrument_flange`` ``(..., 4, 4)``.
    """
    alpha, a, beta, theta0, d = model.table(x).unbind(-1)
    rot, pos = link_transform(alpha, a, beta, theta0 + q, d)
    links = tf.homogeneous(rot, pos) @ spring_transform(theta)
    acc = model.instrument_from_base(x) @ model.T_base_0.to(q)
    frames = []
    for i in range(links.shape[-3]):  # over joints, not poses: the chain is sequential
        acc = acc @ links[..., i, :, :]
        frames.append(acc)
    return torch.stack(frames, -3), acc @ model.T_n_flange.to(q)


def deformed_tcp_pose(model: ErrorModel, q: torch.Tensor, x: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """``T_instrument_tool`` ``(..., 4, 4)`` of the chain deformed by ``theta`` ``(..., N, 6)``."""
    _, flange = deformed_joint_poses(model, q, x, theta)
    return flange @ model.flange_from_tool(x)


def loaded_tcp_pose(
    model: ErrorModel,
    q: torch.Tensor,
    x: torch.Tensor,
    compliance: torch.Tensor,
    wrench: torch.Tensor,
    *,
    wrench_frame: WrenchFrame = "tool",
    iterations: int = 1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """TCP pose under load: spring equilibrium, then the exact deformed chain.

    With ``iterations = 1`` the springs deform by the VJM law at the unloaded configuration;
    more iterations re-evaluate ``theta = C J(theta)^T W(theta)`` at the deformed configuration
    (a wrench fixed in the tool frame turns with the tool), a fixed point that converges
    geometrically because ``|C J^T W|`` is of order 1e-3.

    Returns:
        ``(T_instrument_tool (..., 4, 4), theta (..., N, 6))``.
    """
    compliance = compliance.to(q)
    n = model.robot.dof
    theta = torch.zeros(*q.shape[:-1], n, 6, dtype=q.dtype, device=q.device)
    tool = model.flange_from_tool(x)
    for _ in range(max(1, iterations)):
        frames, flange = deformed_joint_poses(model, q, x, theta)
        pose = flange @ tool
        # J_i of the deformed chain: the twist of spring i acts at frame i after its own spring,
        # which to first order is the same as before it.
        blocks = twist_blocks(frames, pose[..., :3, 3])
        theta = spring_deformations(blocks, compliance, wrench_in_instrument(wrench, pose, wrench_frame))
    return deformed_tcp_pose(model, q, x, theta), theta


def rederive_parameters(
    model: ErrorModel,
    x: torch.Tensor,
    theta: torch.Tensor,
    *,
    parallel_threshold_rad: float = DEFAULT_PARALLEL_THRESHOLD_RAD,
) -> AxisFrames:
    """MDH(+beta) table of the chain held at the fixed deformation ``theta`` ``(N, 6)``.

    The deformed joint axes are read at ``q = 0`` in the ``base`` frame (axis ``i`` is the z axis
    of the deformed frame *before* joint ``i`` rotates, i.e. including the springs of joints
    ``1..i-1``), and the axis method builds Craig frames on them. Chaining the returned
    ``T_base_0``, table and ``T_n_flange`` reproduces the deformed ``T_base_flange`` at every
    ``q`` (not only at zero), since a fixed deformation only changes the fixed links.

    Note: a real deformation depends on the pose and the load; the re-derived table describes
    the robot at that one deformation (e.g. a constant payload near one working pose).
    """
    x = x.to(torch.float64)
    theta = theta.to(torch.float64)
    n = model.robot.dof
    zero = torch.zeros(n, dtype=torch.float64, device=theta.device)
    alpha, a, beta, theta0, d = model.table(x).unbind(-1)
    rot, pos = link_transform(alpha, a, beta, theta0 + zero, d)
    links = tf.homogeneous(rot, pos)
    springs = spring_transform(theta)
    acc = model.T_base_0.to(theta)
    points, directions = [], []
    for i in range(n):
        acc = acc @ links[i]
        points.append(acc[:3, 3])
        directions.append(acc[:3, 2])
        acc = acc @ springs[i]
    T_base_flange = acc @ model.T_n_flange.to(theta)
    return mdh_from_axes(
        torch.stack(points),
        torch.stack(directions),
        T_base_flange,
        parallel_threshold_rad=parallel_threshold_rad,
    )
