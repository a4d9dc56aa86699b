"""Digital twin of a stiffness loading rig: known joint springs, planned or random wrenches, a tracker.

At each pose within the joint limits the rig measures the unloaded TCP, applies a wrench at the
TCP (force and moment in the ``tool`` frame, as the F/T sensor reports them) and measures the
loaded TCP. The poses and wrenches are either random (random poses; random directions, magnitudes
up to the rig's limits) or those of a loading plan (:mod:`torchcal.stiffness.plan`: poses chosen
from random candidates, wrenches at the rig's limits), designed at the middle of the prior
stiffness range, not at the truth. The truth is the
deformed chain of :mod:`torchcal.stiffness.deformed` with the spring equilibrium re-evaluated on
the deformed structure (not the first-order VJM law that identification uses), so the model is
checked against something it does not contain by construction. Tracker noise is added to both
the loaded and the unloaded measurement (positions, and orientations of a 6-DoF probe).

By default the joints yield only about their axes (the classic model). With ``off_axis > 0``
they also yield off them, as gearboxes, bearings and links do: every diagonal entry of a joint's
6-D compliance (:mod:`torchcal.stiffness.vjm`) is then non-zero (:func:`with_off_axis`).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from torchcal.core.io import atomic_write_text
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.joint_jacobian import geometric_jacobian
from torchcal.kinematics.robot import RobotModel, default_robot_path, load_robot
from torchcal.stiffness.deformed import loaded_tcp_pose
from torchcal.stiffness.experiment import StiffnessData
from torchcal.stiffness.identify import (
    DEFAULT_SIGMA_POSITION_M,
    DEFAULT_SIGMA_ROTATION_RAD,
    classic_names,
)
from torchcal.stiffness.plan import (
    LoadingPlan,
    log_stiffness_jacobian,
    plan_loading,
    predicted_relative_std,
)
from torchcal.stiffness.vjm import WrenchFrame, classic_compliance

MAIN_AXIS_RANGE_NM_PER_RAD = (1e5, 5e5)
WRIST_RANGE_NM_PER_RAD = (1e4, 5e4)
OFF_AXIS_LEVER_M = 0.1
"""Lever (m) of a joint's off-axis translational compliance: ``c_t = off_axis c_rz L^2``."""


@dataclass
class StiffnessTwinConfig:
    """Settings of the loading rig twin (contract units: mm, deg, N, N m).

    Attributes:
        seed: seeds the true stiffness, the instrument placement and the samples.
        max_force_n / max_torque_nm: wrench magnitudes are uniform in ``[0.2, 1] x`` these.
        noise_mm: tracker noise (std per coordinate) on each of the loaded and unloaded points.
        rotation_noise_deg: 6-DoF probe noise (std per rotation component) on each orientation.
        with_rotation: write ``drx, dry, drz``.
        with_unloaded: write the unloaded ``x, y, z`` (the instrument frame is then not ``base``).
        instrument_distance_mm: distance of the tracker from the base (0: instrument = base).
        margin_deg: stay this far inside the joint limits.
        min_singular_value: poses whose TCP Jacobian (m and rad rows) has a smallest singular
            value below this are not used, as a loading plan avoids singular poses (there the
            compensating IK is ill-posed).
        equilibrium_iterations: fixed-point iterations of the spring equilibrium.
        off_axis: off-axis compliance of every joint as a fraction of its on-axis compliance
            (0: the joints yield only about their axes; see :func:`with_off_axis`).
    """

    seed: int = 0
    max_force_n: float = 300.0
    max_torque_nm: float = 30.0
    noise_mm: float = 0.012
    rotation_noise_deg: float = 0.01
    with_rotation: bool = True
    with_unloaded: bool = True
    instrument_distance_mm: float = 3000.0
    margin_deg: float = 5.0
    min_singular_value: float = 0.02
    equilibrium_iterations: int = 4
    off_axis: float = 0.0


def with_off_axis(compliance: torch.Tensor, off_axis: float) -> torch.Tensor:
    """Joint compliance ``(N, 6, 6)`` (SI, joint frames) that also yields off each joint's axis.

    From each joint's on-axis compliance ``c_rz`` (rad/(N m), entry ``[5, 5]``) the other five
    diagonal entries (the 6-D diagonal that ``parameters=full`` fits) are set to
    ``off_axis c_rz`` for the bending rotations ``rx, ry`` (rad/(N m)) and to
    ``off_axis c_rz L^2`` for the translations ``tx, ty, tz`` (m/N), ``L`` =
    :data:`OFF_AXIS_LEVER_M`: a point ``L`` from the joint moves by the same fraction of what the
    on-axis spring would let it. A rigid joint (``c_rz = 0``) stays rigid.
    """
    if off_axis < 0:
        raise ValueError(f"off_axis must be >= 0, got {off_axis}")
    c = compliance.to(torch.float64).clone()
    on_axis = c[..., 5, 5]
    scale = torch.tensor([OFF_AXIS_LEVER_M**2] * 3 + [1.0, 1.0], dtype=torch.float64, device=c.device)
    index = torch.arange(5, device=c.device)
    c[..., index, index] = off_axis * on_axis.unsqueeze(-1) * scale
    return c


def sample_joint_stiffness(n_joints: int, generator: torch.Generator) -> torch.Tensor:
    """KR6-like stiffness ``(N,)`` N m/rad, log-uniform: axes 1-3 in 1e5..5e5, wrist 1e4..5e4."""
    lo = torch.tensor([MAIN_AXIS_RANGE_NM_PER_RAD[0]] * 3 + [WRIST_RANGE_NM_PER_RAD[0]] * (n_joints - 3))
    hi = torch.tensor([MAIN_AXIS_RANGE_NM_PER_RAD[1]] * 3 + [WRIST_RANGE_NM_PER_RAD[1]] * (n_joints - 3))
    u = torch.rand(n_joints, generator=generator, dtype=torch.float64)
    return torch.exp(torch.log(lo.double()) + u * (torch.log(hi.double()) - torch.log(lo.double())))


def prior_middle_stiffness(n_joints: int) -> torch.Tensor:
    """Geometric middle ``(N,)`` N m/rad of the ranges :func:`sample_joint_stiffness` draws from.

    What a rig engineer would assume before the experiment: the loading plan is designed here.
    """
    lo = [MAIN_AXIS_RANGE_NM_PER_RAD[0]] * 3 + [WRIST_RANGE_NM_PER_RAD[0]] * (n_joints - 3)
    hi = [MAIN_AXIS_RANGE_NM_PER_RAD[1]] * 3 + [WRIST_RANGE_NM_PER_RAD[1]] * (n_joints - 3)
    return torch.tensor([math.sqrt(a * b) for a, b in zip(lo, hi)], dtype=torch.float64)


def _random_directions(n: int, generator: torch.Generator) -> torch.Tensor:
    v = torch.randn(n, 3, generator=generator, dtype=torch.float64)
    return v / v.norm(dim=-1, keepdim=True)


class StiffnessTwin:
    """A true robot with joint springs and the rig that measures it.

    Args:
        config: rig settings.
        robot: nominal robot (default: the embedded twin-kr6).
        compliance: true ``(N, 6, 6)`` joint compliance (default: classic, sampled stiffness);
            with ``config.off_axis > 0`` its off-axis diagonal is set by :func:`with_off_axis`.
        x_true: true geometry (error-layer vector, base part ignored); nominal by default.
        device: where tensors are created.
    """

    def __init__(
        self,
        config: StiffnessTwinConfig | None = None,
        *,
        robot: RobotModel | None = None,
        compliance: torch.Tensor | None = None,
        x_true: torch.Tensor | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        config = config if config is not None else StiffnessTwinConfig()
        self.config = config
        self.device = torch.device(device)
        self.robot = robot if robot is not None else load_robot(default_robot_path())
        gen = torch.Generator().manual_seed(config.seed)
        self.joint_stiffness = sample_joint_stiffness(self.robot.dof, gen).to(self.device)
        if compliance is None:
            compliance = classic_compliance(self.joint_stiffness)
        else:  # the truth file reports the given springs about the joint axes (inf: rigid)
            self.joint_stiffness = 1.0 / compliance[..., 5, 5].to(self.device, torch.float64)
        if config.off_axis:
            compliance = with_off_axis(compliance, config.off_axis)
        self.compliance = compliance.to(self.device, torch.float64)
        # The tracker a few metres away, arbitrarily rotated about a near-vertical axis.
        T = torch.eye(4, dtype=torch.float64)
        if config.with_unloaded and config.instrument_distance_mm > 0:
            direction = _random_directions(1, gen)[0]
            direction[2] = 0.2 * direction[2].abs()
            direction = direction / direction.norm()
            tilt = 0.1 * torch.randn(3, generator=gen, dtype=torch.float64)
            axis = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) + tilt
            angle = float(torch.rand(1, generator=gen, dtype=torch.float64)) * 2 * math.pi
            T = tf.homogeneous(tf.so3_exp(axis / axis.norm() * angle), direction * config.instrument_distance_mm * 1e-3)
        self.T_instrument_base = T.to(self.device)
        self.model = ErrorModel(self.robot, T_instrument_base=self.T_instrument_base, device=self.device)
        x = self.model.nominal_vector() if x_true is None else x_true.to(self.device, torch.float64).clone()
        x[self.model.layout.base_slice] = 0.0
        self.x_true = x

    # ------------------------------------------------------------------------------ physics

    def unloaded_pose(self, q: torch.Tensor) -> torch.Tensor:
        """True unloaded ``T_instrument_tool`` ``(..., 4, 4)``."""
        return self.model.tcp_pose(q, self.x_true)

    def loaded_pose(self, q: torch.Tensor, wrench: torch.Tensor, wrench_frame: WrenchFrame = "tool") -> torch.Tensor:
        """True loaded ``T_instrument_tool`` ``(..., 4, 4)`` under ``wrench`` ``(..., 6)`` (N, N m)."""
        pose, _ = loaded_tcp_pose(
            self.model,
            q,
            self.x_true,
            self.compliance,
            wrench,
            wrench_frame=wrench_frame,
            iterations=self.config.equilibrium_iterations,
        )
        return pose

    def sample_wrenches(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """Random wrenches ``(n, 6)`` in the ``tool`` frame, magnitudes in ``[0.2, 1] x`` the maxima."""
        c = self.config
        mag = 0.2 + 0.8 * torch.rand(n, 2, generator=generator, dtype=torch.float64)
        f = _random_directions(n, generator) * mag[:, :1] * c.max_force_n
        m = _random_directions(n, generator) * mag[:, 1:] * c.max_torque_nm
        return torch.cat([f, m], -1).to(self.device)

    def measure(self, q: torch.Tensor, wrench: torch.Tensor, generator: torch.Generator) -> StiffnessData:
        """One rig measurement per row of ``q`` ``(B, N)`` rad and ``wrench`` ``(B, 6)`` (tool frame)."""
        c = self.config
        q = q.to(self.device, torch.float64)
        wrench = wrench.to(self.device, torch.float64)
        free, loaded = self.unloaded_pose(q), self.loaded_pose(q, wrench)

        def noise(std: float) -> torch.Tensor:
            return (torch.randn(q.shape[0], 3, generator=generator, dtype=torch.float64) * std).to(self.device)

        sigma_p, sigma_r = c.noise_mm * 1e-3, math.radians(c.rotation_noise_deg)
        p0 = free[:, :3, 3] + noise(sigma_p)
        p1 = loaded[:, :3, 3] + noise(sigma_p)
        # Noisy orientations of both measurements, then the loaded-from-unloaded rotation.
        r0 = tf.so3_exp(noise(sigma_r)) @ free[:, :3, :3]
        r1 = tf.so3_exp(noise(sigma_r)) @ loaded[:, :3, :3]
        rotation = tf.so3_log(r1 @ r0.transpose(-1, -2))
        return StiffnessData(
            q=q,
            wrench=wrench,
            deflection=p1 - p0,
            rotation=rotation if c.with_rotation else None,
            unloaded=p0 if c.with_unloaded else None,
        )

    def sample_poses(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """``n`` random joint vectors ``(n, N)`` rad within the limits, away from singularities."""
        kept: list[torch.Tensor] = []
        count = 0
        for _ in range(100):  # batches of candidates, not a loop over poses
            q = self.robot.sample_joints(2 * n, generator, margin=math.radians(self.config.margin_deg)).to(self.device)
            _, jac = geometric_jacobian(self.model, q, self.x_true)
            q = q[torch.linalg.svdvals(jac)[:, -1] >= self.config.min_singular_value]
            kept.append(q)
            count += q.shape[0]
            if count >= n:
                return torch.cat(kept)[:n]
        raise ValueError(f"fewer than {n} regular poses found; lower min_singular_value")

    def sample(self, n: int, generator: torch.Generator) -> StiffnessData:
        """``n`` random loaded poses (see :meth:`sample_poses`) with random wrenches."""
        q = self.sample_poses(n, generator)
        return self.measure(q, self.sample_wrenches(n, generator), generator)

    def difference_sigmas(self) -> tuple[float, float]:
        """Noise std of one loaded-minus-unloaded component: position (m), rotation (rad).

        Both measurements are noisy, hence ``sqrt(2)``; a noise-free rig falls back to the
        identification's default weights (the plan needs finite weights).
        """
        c = self.config
        sigma_p = c.noise_mm * 1e-3 * math.sqrt(2.0) or DEFAULT_SIGMA_POSITION_M
        sigma_r = math.radians(c.rotation_noise_deg) * math.sqrt(2.0) or DEFAULT_SIGMA_ROTATION_RAD
        return sigma_p, sigma_r

    def plan(self, n: int, candidates_q: torch.Tensor) -> LoadingPlan:
        """A-optimal loading plan of ``n`` of the candidate poses ``(C, N)`` rad, at the rig's limits.

        Designed on the nominal robot at :func:`prior_middle_stiffness` with the rig's noise,
        for the classic model (one spring per joint axis); the truth is not used.
        """
        c = self.config
        sigma_p, sigma_r = self.difference_sigmas()
        return plan_loading(
            ErrorModel(self.robot, device=self.device),
            candidates_q,
            n,
            prior_middle_stiffness(self.robot.dof),
            max_force_n=c.max_force_n,
            max_torque_nm=c.max_torque_nm,
            with_rotation=c.with_rotation,
            sigma_position_m=sigma_p,
            sigma_rotation_rad=sigma_r,
        )

    def sample_planned(
        self, n: int, generator: torch.Generator, n_candidates: int | None = None
    ) -> tuple[StiffnessData, LoadingPlan]:
        """``n`` loaded poses of the loading plan chosen from ``n_candidates`` (default ``2 n``)
        random regular poses (see :meth:`sample_poses`), measured by the rig."""
        n_candidates = 2 * n if n_candidates is None else n_candidates
        plan = self.plan(n, self.sample_poses(n_candidates, generator))
        return self.measure(plan.q, plan.wrench, generator), plan

    def predicted_relative_std(self, q: torch.Tensor, wrench: torch.Tensor) -> dict[str, float]:
        """Relative std of each ``k_j{i}_rz`` the fit can expect from poses ``q`` and tool-frame
        ``wrench`` at the true stiffness and geometry (the rig's noise, classic model)."""
        sigma_p, sigma_r = self.difference_sigmas()
        names = classic_names(self.robot.dof)
        jac = log_stiffness_jacobian(
            self.model,
            q.to(self.device, torch.float64),
            self.x_true,
            wrench.to(self.device, torch.float64),
            names,
            self.joint_stiffness,
            with_rotation=self.config.with_rotation,
            sigma_position_m=sigma_p,
            sigma_rotation_rad=sigma_r,
        )
        return {name: float(v) for name, v in zip(names, predicted_relative_std(jac))}

    def noise_floor_mm(self) -> float:
        """RMS 3-D norm of the deflection noise (loaded and unloaded points both noisy), mm."""
        return math.sqrt(2.0 * 3.0) * self.config.noise_mm

    def truth_dict(self) -> dict:
        """Known truth, JSON-ready: stiffness (N m/rad), compliance, instrument frame, noise."""
        names = [f"k_j{i}_rz" for i in range(1, self.robot.dof + 1)]
        config = asdict(self.config)
        if not self.config.off_axis:  # twins that yield only about their axes: truth files as before
            del config["off_axis"]
        return {
            "robot": self.robot.name,
            "units": {"stiffness": "N m/rad (rotations), N/m (translations)", "compliance": "SI", "lengths": "mm"},
            "joint_stiffness_nm_per_rad": {n: float(k) for n, k in zip(names, self.joint_stiffness)},
            "compliance_si": self.compliance.tolist(),
            "T_instrument_base": {
                "rotation": self.T_instrument_base[:3, :3].tolist(),
                "translation_mm": (self.T_instrument_base[:3, 3] * 1e3).tolist(),
            },
            "deflection_noise_floor_rms_mm": self.noise_floor_mm(),
            "config": config,
        }


# ------------------------------------------------------------------------------------ files


def stiffness_csv_text(data: StiffnessData) -> str:
    """The contract CSV of ``data``: deg, N, N m, mm (and deg for rotations)."""
    n = data.n_joints
    header = [f"q{i}" for i in range(1, n + 1)] + ["fx", "fy", "fz", "tx", "ty", "tz", "dx", "dy", "dz"]
    blocks = [data.q * (180.0 / math.pi), data.wrench, data.deflection * 1e3]
    if data.rotation is not None:
        header += ["drx", "dry", "drz"]
        blocks.append(data.rotation * (180.0 / math.pi))
    if data.unloaded is not None:
        header += ["x", "y", "z"]
        blocks.append(data.unloaded * 1e3)
    table = torch.cat([b.cpu() for b in blocks], -1).tolist()
    lines = [",".join(header)] + [",".join(f"{v:.12g}" for v in row) for row in table]
    return "\n".join(lines) + "\n"


def write_stiffness_csv(path: str | Path, data: StiffnessData) -> Path:
    """Write ``data`` as a contract stiffness CSV, atomically."""
    path = Path(path)
    atomic_write_text(path, stiffness_csv_text(data))
    return path


def write_stiffness_case(
    out: str | Path,
    config: StiffnessTwinConfig | None = None,
    *,
    n_train: int = 120,
    n_test: int = 200,
    robot: RobotModel | None = None,
    compliance: torch.Tensor | None = None,
    plan: str = "optimal",
    plan_candidates: int | None = None,
) -> dict[str, Path]:
    """Write ``stiffness_train.csv``, ``stiffness_test.csv`` and ``stiffness_truth.json`` to ``out``.

    ``robot`` and ``compliance`` are handed to :class:`StiffnessTwin` (defaults: twin-kr6, sampled).
    ``plan="optimal"`` loads the training poses as :meth:`StiffnessTwin.sample_planned` does (from
    ``plan_candidates`` random poses, default ``2 n_train``) and reports the plan and the predicted
    relative std of every stiffness in the truth file; ``plan="random"`` writes the random
    loading of earlier versions, file for file. The test poses are randomly loaded in both.
    """
    if plan not in ("optimal", "random"):
        raise ValueError(f"plan must be 'optimal' or 'random', got {plan!r}")
    out = Path(out)
    twin = StiffnessTwin(config, robot=robot, compliance=compliance)
    config = config if config is not None else StiffnessTwinConfig()
    gen = torch.Generator().manual_seed(config.seed + 104729)
    paths = {name: out / name for name in ("stiffness_train.csv", "stiffness_test.csv", "stiffness_truth.json")}
    truth = twin.truth_dict()
    if plan == "random":  # the stream of earlier versions: train, then test, from one generator
        train = twin.sample(n_train, gen)
    else:
        candidates = 2 * n_train if plan_candidates is None else plan_candidates
        train, loading = twin.sample_planned(n_train, gen, candidates)
        truth["loading_plan"] = {
            "plan": "optimal",
            "candidate_poses": candidates,
            **loading.as_dict(),
            "predicted_relative_std_at_truth": twin.predicted_relative_std(train.q, train.wrench),
        }
    write_stiffness_csv(paths["stiffness_train.csv"], train)
    write_stiffness_csv(paths["stiffness_test.csv"], twin.sample(n_test, gen))
    atomic_write_text(paths["stiffness_truth.json"], json.dumps(truth, indent=2) + "\n")
    return paths
