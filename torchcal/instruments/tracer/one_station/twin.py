"""A one-station twin case: a true robot measured by one draw-wire (cable) sensor.

The cable runs from an anchor ``A`` fixed in the cell to an attachment point on the flange (the
true tool point), and reads ``l = |P(q) - A| + c`` with an unknown zero offset ``c``. The poses
are drawn in a ball of the working volume (as the tracer case), the held-out poses from the same
ball, so ``test.csv`` scores the model on new poses of the same set-up.

Frames: anchor and points in the robot ``base`` frame (the cable has no frame of its own).

Files: ``robot.yaml`` (nominal), ``lengths.csv`` and ``test.csv`` (``q1..qN, l1``: deg, mm) and
``truth.json`` (true robot, anchor, offset, noise and the noise floor of ``test.csv``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from torchcal.core.errors import TorchcalError
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.core.overrides import check_range
from torchcal.instruments.tracer.twin_case import (
    sample_in_sphere,
    true_base_points,
    write_lengths_csv,
)
from torchcal.kinematics.robot import robot_to_yaml
from torchcal.sim.twin import Twin, TwinConfig


@dataclass
class LengthStationTwinConfig:
    """Settings of a one-station case (mm, deg).

    Attributes:
        robot: robot file (default: the embedded twin-kr6).
        seed: random seed of robot errors, poses and noise.
        n_train / n_test: poses in ``lengths.csv`` / ``test.csv``.
        anchor_mm: the cable's anchor in the robot ``base`` frame.
        offset_mm: the sensor's zero offset ``c`` (``l = |P - A| + c``).
        noise_mm: 1-sigma of each length reading.
        sphere_center_mm / sphere_radius_mm: the ball of the working volume the poses lie in.
        length_error_mm / angle_error_deg / tool_error_mm: robot errors (as the tracker twin).
        margin_deg: distance kept from joint limits when sampling poses.
    """

    robot: str | None = None
    seed: int = 0
    n_train: int = 200
    n_test: int = 100
    anchor_mm: list[float] = field(default_factory=lambda: [900.0, -700.0, 100.0])
    offset_mm: float = -300.0
    noise_mm: float = 0.01
    sphere_center_mm: list[float] = field(default_factory=lambda: [600.0, 0.0, 600.0])
    sphere_radius_mm: float = 400.0
    length_error_mm: float = 0.3
    angle_error_deg: float = 0.03
    tool_error_mm: float = 0.5
    margin_deg: float = 5.0

    def __post_init__(self) -> None:
        """Refuse settings without a physical meaning before anything is simulated."""
        check_range(self, "n_train", low=20, high=1_000_000)
        check_range(self, "n_test", low=1, high=1_000_000)
        check_range(self, "noise_mm", low=0.0)
        check_range(self, "sphere_radius_mm", low=0.0, low_open=True)
        check_range(self, "offset_mm")
        for name in ("anchor_mm", "sphere_center_mm"):
            value = getattr(self, name)
            if len(value) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in value):
                raise TorchcalError(f"{name} must be three finite numbers (x, y, z in mm), got {value}")

    @property
    def noise_floor_rms_mm(self) -> float:
        """Length RMS of a perfect model on ``test.csv``: the reading noise."""
        return self.noise_mm


@dataclass
class LengthStationCase:
    """A simulated one-station session (SI units; ``q`` rad, lengths m, ``base`` frame)."""

    config: LengthStationTwinConfig
    twin: Twin
    q_train: torch.Tensor
    q_test: torch.Tensor
    lengths_train: torch.Tensor
    lengths_test: torch.Tensor
    anchor: torch.Tensor


def simulate_length_station_case(config: LengthStationTwinConfig) -> LengthStationCase:
    """Build the true robot and read the cable at training and held-out poses."""
    twin = Twin.create(TwinConfig(
        robot=config.robot, seed=config.seed, length_error_mm=config.length_error_mm,
        angle_error_deg=config.angle_error_deg, tool_error_mm=config.tool_error_mm,
    ))
    gen = torch.Generator().manual_seed(config.seed + 15485863)
    center = torch.tensor(config.sphere_center_mm, dtype=torch.float64) * 1e-3
    q_all = sample_in_sphere(twin, config.n_train + config.n_test, center, config.sphere_radius_mm * 1e-3,
                             math.radians(config.margin_deg), gen)
    anchor = torch.tensor(config.anchor_mm, dtype=torch.float64) * 1e-3
    true = (true_base_points(twin, q_all) - anchor).norm(dim=-1) + config.offset_mm * 1e-3
    if bool((true <= 0).any()):
        raise TorchcalError("some lengths come out at or below zero: move the anchor away from the ball of poses "
                            "or raise offset_mm")
    read = true + torch.randn(true.shape, generator=gen, dtype=torch.float64) * config.noise_mm * 1e-3
    n = config.n_train
    return LengthStationCase(config, twin, q_all[:n], q_all[n:], read[:n], read[n:], anchor)


def write_length_station_case(out: str | Path, config: LengthStationTwinConfig) -> dict[str, Path]:
    """Write ``robot.yaml``, ``lengths.csv``, ``test.csv`` and ``truth.json`` of a one-station case."""
    out = Path(out)
    case = simulate_length_station_case(config)
    paths = {name: out / name for name in ("robot.yaml", "lengths.csv", "test.csv", "truth.json")}
    atomic_write_text(paths["robot.yaml"], robot_to_yaml(case.twin.robot))
    write_lengths_csv(paths["lengths.csv"], case.q_train, case.lengths_train.unsqueeze(-1))
    write_lengths_csv(paths["test.csv"], case.q_test, case.lengths_test.unsqueeze(-1))
    truth = case.twin.truth_dict()
    truth["config"] = asdict(config)
    truth.update({
        "instrument": "length_station",
        "frames": "anchor and robot in the robot base frame",
        "anchor_mm": (case.anchor * 1e3).tolist(),
        "offset_mm": config.offset_mm,
        "noise_mm": config.noise_mm,
        "noise_floor_rms_mm": config.noise_floor_rms_mm,
    })
    atomic_write_json(paths["truth.json"], truth)
    return paths
