"""Test helpers shared by the compensator tests: a residual head with a known closed form."""

import torch


class KnownResidual(torch.nn.Module):
    """A hand-made residual head: ``r(q) = c + a sin(q1) e_z`` (m, base frame)."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("c", torch.tensor([2e-4, -1e-4, 3e-4], dtype=torch.float64))
        self.register_buffer("a", torch.tensor([0.0, 0.0, 1.5e-4], dtype=torch.float64))

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        return self.c + torch.sin(q[:, :1]) * self.a


def residual_value(q: torch.Tensor) -> torch.Tensor:
    return torch.tensor([2e-4, -1e-4, 3e-4], dtype=torch.float64) + torch.sin(q[:, :1]) * torch.tensor([0.0, 0.0, 1.5e-4], dtype=torch.float64)


def nominal_tcp_pose(robot, q):
    pose = robot.flange_pose(q).clone()
    pose[..., :3, 3] = pose[..., :3, :3] @ robot.tool + pose[..., :3, 3]
    return pose
