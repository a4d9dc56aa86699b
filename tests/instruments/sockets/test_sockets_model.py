"""The socket problem's hand-assembled Jacobian against central finite differences."""

from __future__ import annotations

import torch

from torchcal.instruments.sockets.data import _assemble
from torchcal.instruments.sockets.fit import make_problem
from torchcal.kinematics.robot import default_robot_path, load_robot


def _data(robot, n=12):
    gen = torch.Generator().manual_seed(3)
    q = robot.sample_joints(n, gen, margin=0.2)
    placement = tuple("a" if i < n // 2 else "b" for i in range(n))
    socket = tuple(i % 2 for i in range(n))
    return _assemble(q, placement, socket, "mem.csv", "0", tuple(range(2, n + 2)))


def test_jacobian_matches_finite_differences_with_gravity_terms():
    robot = load_robot(default_robot_path())
    data = _data(robot)
    problem, z0 = make_problem(robot, data, gravity_points=("elbow", "tcp"))
    gen = torch.Generator().manual_seed(5)
    z = z0 + 1e-3 * torch.randn(z0.shape, generator=gen, dtype=torch.float64)
    r, jac = problem.jacobian(z)
    assert torch.allclose(r, problem.residuals(z))
    h = 1e-7
    numeric = []
    for col in problem.free.tolist():
        dz = torch.zeros_like(z)
        dz[col] = h
        numeric.append((problem.residuals(z + dz) - problem.residuals(z - dz)) / (2 * h))
    numeric = torch.stack(numeric, -1)
    scale = numeric.abs().max()
    assert float((jac - numeric).abs().max() / scale) < 1e-6


def test_distance_rows_make_the_scale():
    robot = load_robot(default_robot_path())
    data = _data(robot)
    problem, z0 = make_problem(robot, data, distance_mm=50.0, distance_weight=1.0)
    _, c = problem.split(z0)
    r = problem.residuals(z0)[-2:]
    expected = torch.stack([(c[a] - c[b]).norm() - 0.05 for a, b in problem.pairs.tolist()])
    assert torch.allclose(r, expected)
