"""A laser-tracer twin case: a true robot measured from several tracer stations.

As in the tracer patent, the reflector visits poses whose TCP lies in a sphere of the working
volume, and one tracer is set up in turn at ``n_stations`` stations around that sphere (a regular
tetrahedron for four, a Fibonacci sphere otherwise, randomly oriented). The robot runs the same
program once per station, so robot repeatability enters every length on its own.

Frames: stations and points are in the robot ``base`` frame (the tracer has no frame of its own);
the held-out check file ``test.csv`` holds laser-*tracker* points of other poses in the same
sphere, in the twin's tracker frame (``instrument``), so a tracer-calibrated model is scored with
``torchcal evaluate --register``.

Files: ``robot.yaml`` (nominal), ``lengths.csv`` (``q1..qN, l1..lM``: deg, mm, empty where a
length was lost), ``test.csv`` (``q1..qN, x, y, z``: deg, mm) and ``truth.json`` (true robot,
stations, dead paths, noise, the test noise floor and the predicted multilateration accuracy).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from torchcal.core.errors import TorchcalError
from torchcal.core.io import atomic_write_json, atomic_write_text
from torchcal.data.measurements import Measurements, write_measurements_csv
from torchcal.instruments.tracer.lengths import LengthSigma, station_distances
from torchcal.instruments.tracer.multilateration import predict_covariance
from torchcal.instruments.tracer.plan import _spread_directions
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.robot import robot_to_yaml
from torchcal.kinematics.transforms import so3_exp
from torchcal.sim.twin import Twin, TwinConfig


@dataclass
class TracerTwinConfig:
    """Settings of a tracer twin case (report units: mm, um, deg).

    Attributes:
        robot: robot file (default: the embedded twin-kr6).
        seed: random seed of robot errors, stations, poses and noise.
        n_train: poses in ``lengths.csv``.
        n_test: tracker-measured poses in ``test.csv``.
        n_stations: tracer stations (``l1..lM``).
        sphere_center_mm / sphere_radius_mm: the sphere of the working volume (``base`` frame)
            the TCP visits.
        station_distance_mm: distance of the stations from the sphere centre (default
            ``2.5 * sphere_radius_mm``).
        sigma_constant_um / sigma_per_m_um: length noise ``sigma(L) = c + k L``.
        repeatability_mm: robot repeatability per axis, drawn anew for every station visit (and
            for every test pose).
        loss_probability: chance that any one length is lost (empty cell).
        test_sigma_mm: per-axis noise of the tracker points in ``test.csv``.
        length_error_mm / angle_error_deg / tool_error_mm: robot errors (as the tracker twin).
        margin_deg: distance kept from joint limits when sampling poses.
    """

    robot: str | None = None
    seed: int = 0
    n_train: int = 60
    n_test: int = 200
    n_stations: int = 4
    sphere_center_mm: list[float] = field(default_factory=lambda: [600.0, 0.0, 600.0])
    sphere_radius_mm: float = 400.0
    station_distance_mm: float | None = None
    sigma_constant_um: float = 0.2
    sigma_per_m_um: float = 0.3
    repeatability_mm: float = 0.0
    loss_probability: float = 0.0
    test_sigma_mm: float = 0.001
    length_error_mm: float = 0.3
    angle_error_deg: float = 0.03
    tool_error_mm: float = 0.5
    margin_deg: float = 5.0

    @property
    def sigma(self) -> LengthSigma:
        return LengthSigma(self.sigma_constant_um * 1e-6, self.sigma_per_m_um * 1e-6)

    @property
    def noise_floor_rms_mm(self) -> float:
        """RMS 3-D error of a perfect model on ``test.csv``: tracker noise plus repeatability."""
        return math.sqrt(3.0 * (self.test_sigma_mm**2 + self.repeatability_mm**2))


@dataclass
class TracerCase:
    """A simulated tracer session and its held-out check, SI units.

    Attributes:
        twin: the true robot (``twin.x_true``; its base slice is the tracker frame of the test).
        q_train: ``(n, N)`` rad. points_train: ``(n, 3)`` true TCP, ``base`` frame, m.
        lengths: ``(n, m)`` readings, m, NaN where lost. stations: ``(m, 3)`` m, ``base``.
        dead_paths: ``(m,)`` m. test: tracker points of held-out poses (``instrument`` frame).
        test_true_base: ``(n_test, 3)`` noise-free test TCP points, ``base`` frame, m.
    """

    config: TracerTwinConfig
    twin: Twin
    q_train: torch.Tensor
    points_train: torch.Tensor
    lengths: torch.Tensor
    stations: torch.Tensor
    dead_paths: torch.Tensor
    test: Measurements
    test_true_base: torch.Tensor

    def true_base_points(self, q: torch.Tensor) -> torch.Tensor:
        """Noise-free TCP ``(B, 3)`` in the robot ``base`` frame, m."""
        return true_base_points(self.twin, q)


def true_base_points(twin: Twin, q: torch.Tensor) -> torch.Tensor:
    """Noise-free TCP ``(B, 3)`` of the true robot in its ``base`` frame, m."""
    x = twin.x_true.clone()
    x[twin.model.layout.base_slice] = 0.0
    return ErrorModel(twin.robot).tcp_position(q, x)


def sample_in_sphere(twin: Twin, n: int, center_m: torch.Tensor, radius_m: float, margin_rad: float,
                     generator: torch.Generator) -> torch.Tensor:
    """``(n, N)`` joints (rad) within limits whose true TCP lies in the ball (``base`` frame)."""
    found: list[torch.Tensor] = []
    total = 0
    for _ in range(200):  # rejection sampling, batched; a ball of the working volume keeps ~1-5 %
        q = twin.robot.sample_joints(20000, generator, margin=margin_rad)
        inside = (true_base_points(twin, q) - center_m).norm(dim=-1) <= radius_m
        found.append(q[inside])
        total += int(inside.sum())
        if total >= n:
            return torch.cat(found)[:n]
    raise TorchcalError(
        f"the sphere (centre {(center_m * 1e3).tolist()} mm, radius {radius_m * 1e3:g} mm) is hardly reachable: "
        f"found {total} of {n} poses; move it into the working volume"
    )


def simulate_tracer_case(config: TracerTwinConfig) -> TracerCase:
    """Build the true robot and simulate the tracer session and the held-out tracker check."""
    if config.n_stations < 4:
        raise TorchcalError(f"a tracer case needs at least 4 stations, got {config.n_stations}")
    if config.n_train < 16:
        raise TorchcalError(f"a tracer case needs at least 16 poses, got {config.n_train}")
    twin = Twin.create(TwinConfig(
        robot=config.robot, seed=config.seed, length_error_mm=config.length_error_mm,
        angle_error_deg=config.angle_error_deg, tool_error_mm=config.tool_error_mm,
    ))
    gen = torch.Generator().manual_seed(config.seed + 104729)
    center = torch.tensor(config.sphere_center_mm, dtype=torch.float64) * 1e-3
    radius = config.sphere_radius_mm * 1e-3
    margin = math.radians(config.margin_deg)
    q_all = sample_in_sphere(twin, config.n_train + config.n_test, center, radius, margin, gen)
    q_train, q_test = q_all[: config.n_train], q_all[config.n_train :]

    dist = (config.station_distance_mm or 2.5 * config.sphere_radius_mm) * 1e-3
    rot = so3_exp(math.pi * torch.randn(3, generator=gen, dtype=torch.float64))
    stations = center + dist * _spread_directions(config.n_stations) @ rot.T

    points = true_base_points(twin, q_train)
    # interferometers zeroed with the reflector at the first pose: dead path = that distance
    dead = station_distances(points[:1], stations)[0]
    n, m = points.shape[0], stations.shape[0]
    repeat = torch.randn(n, m, 3, generator=gen, dtype=torch.float64) * config.repeatability_mm * 1e-3
    actual = (points.unsqueeze(1) + repeat - stations).norm(dim=-1)  # one robot visit per station
    sigma = config.sigma
    lengths = actual - dead + sigma.sample(actual, gen)
    if config.loss_probability > 0:
        if not config.loss_probability < 1:
            raise TorchcalError(f"loss_probability must be in [0, 1), got {config.loss_probability}")
        lost = torch.rand(n, m, generator=gen, dtype=torch.float64) < config.loss_probability
        lengths = torch.where(lost, torch.nan, lengths)

    test_base = true_base_points(twin, q_test)
    t_ib = twin.T_instrument_base()
    test_true = test_base @ t_ib[:3, :3].T + t_ib[:3, 3]
    noise = math.hypot(config.test_sigma_mm, config.repeatability_mm) * 1e-3
    test = Measurements(q=q_test, position=test_true + torch.randn(test_true.shape, generator=gen, dtype=torch.float64) * noise)
    return TracerCase(config, twin, q_train, points, lengths, stations, dead, test, test_base)


def write_lengths_csv(path: str | Path, q: torch.Tensor, lengths_m: torch.Tensor) -> None:
    """Write a contract tracer file (deg, mm; empty cell where a length is NaN) atomically."""
    cols = [f"q{i}" for i in range(1, q.shape[1] + 1)] + [f"l{j}" for j in range(1, lengths_m.shape[1] + 1)]
    lines = [",".join(cols)]
    for qi, li in zip((q * (180.0 / math.pi)).tolist(), (lengths_m * 1e3).tolist()):
        cells = [f"{v:.10f}" for v in qi] + ["" if math.isnan(v) else f"{v:.7f}" for v in li]
        lines.append(",".join(cells))
    atomic_write_text(path, "\n".join(lines) + "\n")


def truth_dict(case: TracerCase) -> dict:
    """Everything a check needs: robot truth, stations and dead paths, noise, predicted accuracy."""
    twin, config = case.twin, case.config
    seen = torch.isfinite(case.lengths)
    predicted = None
    try:
        cov, _ = predict_covariance(case.points_train, case.stations, config.sigma, visible=seen)
        n = case.points_train.shape[0]
        predicted = math.sqrt(float(cov.diagonal()[: 3 * n].sum()) / n) * 1e6
    except TorchcalError:  # a sparse loss pattern can leave the lengths alone underdetermined
        pass
    truth = twin.truth_dict()
    truth["config"] = asdict(config)
    truth.update({
        "instrument": "tracer",
        "frames": "stations and robot in the robot base frame; test.csv in the tracker frame T_instrument_base",
        "stations_mm": (case.stations * 1e3).tolist(),
        "dead_paths_mm": (case.dead_paths * 1e3).tolist(),
        "length_sigma": {"constant_um": config.sigma_constant_um, "per_m_um": config.sigma_per_m_um},
        "repeatability_mm": config.repeatability_mm,
        "test_sigma_mm": config.test_sigma_mm,
        "noise_floor_rms_mm": config.noise_floor_rms_mm,
        "predicted_point_rms_um": predicted,
        "n_lengths_lost": int((~seen).sum()),
    })
    return truth


def write_tracer_case(out: str | Path, config: TracerTwinConfig) -> dict[str, Path]:
    """Write ``robot.yaml``, ``lengths.csv``, ``test.csv`` and ``truth.json`` of a tracer case."""
    out = Path(out)
    case = simulate_tracer_case(config)
    paths = {name: out / name for name in ("robot.yaml", "lengths.csv", "test.csv", "truth.json")}
    atomic_write_text(paths["robot.yaml"], robot_to_yaml(case.twin.robot))
    write_lengths_csv(paths["lengths.csv"], case.q_train, case.lengths)
    write_measurements_csv(paths["test.csv"], case.test.q, case.test.position)
    atomic_write_json(paths["truth.json"], truth_dict(case))
    return paths
