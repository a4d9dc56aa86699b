"""A socket twin: a true robot with known errors putting its ball into two-socket fixtures.

For each placement a fixture stands at a reachable point of the true robot: socket 0 there,
socket 1 ``distance_mm`` away in a random horizontal direction. Configurations reaching each
socket come from position-only IK on the true robot (:func:`torchcal.kinematics.ik.solve_ik`)
started from random perturbations of a seed configuration, so the ball reaches the socket with
many different orientations. The commanded joints written are the true ones plus encoder noise.

Frames: everything is in the robot ``base`` frame (there is no instrument). Files:
``robot.yaml`` (nominal), ``sockets.csv`` (training placements), ``sockets_test.csv`` (other
placements), ``truth.json`` (true parameters in mm/deg, the socket points in mm).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from torchcal.core.errors import TorchcalError
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.core.overrides import check_range
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import solve_ik
from torchcal.kinematics.robot import robot_to_yaml
from torchcal.sim.twin import Twin, TwinConfig


@dataclass
class SocketsTwinConfig:
    """Settings of a socket twin case (mm, deg).

    Attributes:
        robot: robot file (default: the embedded twin-kr6).
        seed: random seed of robot errors, fixtures, configurations and noise.
        n_placements / n_test_placements: fixtures written to ``sockets.csv`` / ``sockets_test.csv``.
        configurations_per_socket: configurations per socket and placement.
        distance_mm: socket-to-socket distance of the fixture.
        joint_noise_deg: 1-sigma of the commanded-joint (encoder) noise per joint.
        spread_deg: 1-sigma of the random start perturbation of the IK (orientation variety).
        length_error_mm / angle_error_deg / tool_error_mm: robot errors (as the tracker twin).
        margin_deg: distance kept from joint limits.
    """

    robot: str | None = None
    seed: int = 0
    n_placements: int = 2
    n_test_placements: int = 2
    configurations_per_socket: int = 40
    distance_mm: float = 50.0
    joint_noise_deg: float = 0.001
    spread_deg: float = 35.0
    length_error_mm: float = 0.3
    angle_error_deg: float = 0.03
    tool_error_mm: float = 0.5
    margin_deg: float = 5.0

    def __post_init__(self) -> None:
        """Refuse a fixture that cannot be built (sockets 0 mm apart carry no scale) and empty counts."""
        check_range(self, "distance_mm", low=0.0, low_open=True)
        for name in ("n_placements", "n_test_placements", "configurations_per_socket"):
            check_range(self, name, low=1, high=100_000)
        for name in ("joint_noise_deg", "spread_deg", "length_error_mm", "angle_error_deg", "tool_error_mm", "margin_deg"):
            check_range(self, name, low=0.0)


def _true_model(twin: Twin) -> tuple[ErrorModel, torch.Tensor]:
    x = twin.x_true.clone()
    x[twin.model.layout.base_slice] = 0.0
    return ErrorModel(twin.robot), x


def _reach(model: ErrorModel, x: torch.Tensor, target: torch.Tensor, seed_q: torch.Tensor, n: int,
           config: SocketsTwinConfig, gen: torch.Generator) -> torch.Tensor:
    """``(n, N)`` true joints (rad) that put the true ball centre at ``target`` (m, base)."""
    lim = model.robot.joint_limits
    margin = math.radians(config.margin_deg)
    found: list[torch.Tensor] = []
    total = 0
    for _ in range(20):
        q0 = seed_q + torch.randn(4 * n, seed_q.numel(), generator=gen, dtype=torch.float64) * math.radians(config.spread_deg)
        q0 = torch.minimum(torch.maximum(q0, lim[:, 0] + margin), lim[:, 1] - margin)
        res = solve_ik(model, x, target.expand(q0.shape[0], 3), q0, position_only=True, max_iterations=100, damping=1e-3)
        ok = res.converged & ((res.q >= lim[:, 0] + margin) & (res.q <= lim[:, 1] - margin)).all(-1)
        found.append(res.q[ok])
        total += int(ok.sum())
        if total >= n:
            return torch.cat(found)[:n]
    raise TorchcalError(f"only {total} of {n} configurations reach a socket at {(target * 1e3).tolist()} mm; "
                        "lower spread_deg or configurations_per_socket")


def simulate_sockets(config: SocketsTwinConfig) -> tuple[Twin, list[dict]]:
    """The true robot and, per placement, ``{name, points (2, 3) m, q (2 n, N) rad commanded, socket (2 n,)}``."""
    if config.n_placements < 1:
        raise TorchcalError(f"a socket case needs at least one placement, got {config.n_placements}")
    twin = Twin.create(TwinConfig(robot=config.robot, seed=config.seed, length_error_mm=config.length_error_mm,
                                  angle_error_deg=config.angle_error_deg, tool_error_mm=config.tool_error_mm))
    model, x = _true_model(twin)
    gen = torch.Generator().manual_seed(config.seed + 65537)
    margin = math.radians(config.margin_deg)
    n = config.configurations_per_socket
    placements = []
    for k in range(config.n_placements + config.n_test_placements):
        seed_q = twin.robot.sample_joints(1, gen, margin=3 * margin)[0]
        p0 = model.tcp_position(seed_q.unsqueeze(0), x)[0]
        angle = float(torch.rand(1, generator=gen, dtype=torch.float64)) * 2 * math.pi
        p1 = p0 + config.distance_mm * 1e-3 * torch.tensor([math.cos(angle), math.sin(angle), 0.0], dtype=torch.float64)
        qs = [_reach(model, x, p, seed_q, n, config, gen) for p in (p0, p1)]
        q = torch.cat(qs)
        q = q + torch.randn(q.shape, generator=gen, dtype=torch.float64) * math.radians(config.joint_noise_deg)
        placements.append({"name": f"fixture{k + 1}", "points": torch.stack([p0, p1]), "q": q,
                           "socket": [0] * n + [1] * n})
    return twin, placements


def _write_csv(path: Path, placements: list[dict], dof: int) -> None:
    lines = ["placement,socket," + ",".join(f"q{j}" for j in range(1, dof + 1))]
    for pl in placements:
        for s, row in zip(pl["socket"], torch.rad2deg(pl["q"]).tolist()):
            lines.append(f"{pl['name']},{s}," + ",".join(f"{v:.9f}" for v in row))
    atomic_write_text(path, "\n".join(lines) + "\n")


def write_sockets_case(out_dir: str | Path, config: SocketsTwinConfig) -> dict[str, Path]:
    """Write ``robot.yaml``, ``sockets.csv``, ``sockets_test.csv`` and ``truth.json``; returns their paths."""
    out = Path(out_dir)
    twin, placements = simulate_sockets(config)
    paths = {name: out / name for name in ("robot.yaml", "sockets.csv", "sockets_test.csv", "truth.json")}
    atomic_write_text(paths["robot.yaml"], robot_to_yaml(twin.robot))
    _write_csv(paths["sockets.csv"], placements[: config.n_placements], twin.robot.dof)
    _write_csv(paths["sockets_test.csv"], placements[config.n_placements :], twin.robot.dof)
    layout = twin.model.layout
    scale = layout.unit_scale()
    truth = {
        "robot": twin.robot.name,
        "units": {"lengths": "mm", "angles": "deg"},
        "frame": "robot base (no instrument)",
        "parameters": {n: float(v * s) for n, v, s in zip(layout.names, twin.x_true.tolist(), scale.tolist())
                       if not n.startswith("base_")},
        "socket_points_mm": {f"{pl['name']}/{s}": (pl["points"][s] * 1e3).tolist() for pl in placements for s in (0, 1)},
        "config": asdict(config),
    }
    atomic_write_json(paths["truth.json"], truth)
    return paths
