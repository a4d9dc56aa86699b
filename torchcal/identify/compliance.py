"""Gravity-induced joint compliance identified with the geometry, from positions alone.

Model. A point weight at ``p`` loads joint ``j`` (axis ``z_j`` through ``o_j``) with the torque
``tau_j = z_j . ((p - o_j) x (-e_z))`` per unit weight (m; ``base`` z up), and the joint gives
way by ``dq_j = c_j tau_j``. Points: ``tcp`` (the nominal TCP: wrist, tool and payload, beyond
every joint) and ``elbow`` (origin of MDH frame 3, beyond joints 1 and 2 only). The coefficient
``c`` (rad per metre of unit-weight lever, i.e. weight over stiffness) is estimated; torques are
evaluated on the *nominal* chain, so ``dq`` is linear in ``c`` and the TCP displacement per
coefficient is ``tau_j`` times the ``theta_j`` column of the position Jacobian.

Why. Cable-driven or light arms (a WAM, a UR) sag measurably under their own weight; a
geometric model cannot express a deflection that changes with the load direction, so it leaves
it in the residual. Which points to use is a model choice made by K-fold cross-validation on the
training poses (``auto``), never on a test set.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from torchcal.data.measurements import Measurements
from torchcal.identify.uncertainty import covariance
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.mdh import chain_frames
from torchcal.kinematics.robot import RobotModel

POINT_SETS: dict[str, tuple[str, ...]] = {"none": (), "wrist": ("tcp",), "elbow+wrist": ("elbow", "tcp")}
ELBOW_FRAME = 3  # MDH frame whose origin stands for the upper-arm mass
_ZERO_COLUMN = 1e-9  # a basis column below this norm (m) has no effect: joint axis along gravity


def gravity_torque_basis(robot: RobotModel, q: torch.Tensor, points: tuple[str, ...]) -> torch.Tensor:
    """Unit-weight gravity torques ``(B, len(points), N)`` in m about each joint, nominal chain, ``base`` z up."""
    model = ErrorModel(robot)
    x = model.nominal_vector()
    frames = chain_frames(q, model.table(x), r_start=model.T_base_0[:3, :3].to(q), p_start=model.T_base_0[:3, 3].to(q))
    axes, origins = frames.stacked("z"), frames.stacked("o")  # (B, N, 3), base frame
    n = robot.dof
    down = torch.tensor([0.0, 0.0, -1.0], dtype=q.dtype, device=q.device)
    out = []
    for name in points:
        if name == "tcp":
            point, beyond = model.tcp_position(q, x), torch.ones(n, dtype=q.dtype)
        elif name == "elbow":
            point = origins[:, min(ELBOW_FRAME, n) - 1]
            beyond = torch.tensor([1.0 if j < ELBOW_FRAME - 1 else 0.0 for j in range(n)], dtype=q.dtype)
        else:
            raise ValueError(f"unknown gravity point '{name}'; choose tcp or elbow")
        lever = point[:, None, :] - origins
        tau = (torch.linalg.cross(lever, down.expand_as(lever), dim=-1) * axes).sum(-1)
        out.append(tau * beyond.to(q.device))
    return torch.stack(out, 1) if out else q.new_zeros(q.shape[0], 0, n)


@dataclass(frozen=True)
class GravityCompliance:
    """Identified compliance: ``points`` and ``coefficients (len(points), N)`` in rad/m."""

    points: tuple[str, ...]
    coefficients: torch.Tensor

    def deflection(self, robot: RobotModel, q: torch.Tensor) -> torch.Tensor:
        """Joint deflection ``(B, N)`` rad at commanded joints ``q`` ``(B, N)`` rad."""
        basis = gravity_torque_basis(robot, q, self.points)
        return (basis * self.coefficients.to(q)).sum(1)

    def effective_joints(self, robot: RobotModel, q: torch.Tensor) -> torch.Tensor:
        """The joint angles the arm actually takes under its own weight, rad."""
        return q + self.deflection(robot, q)

    def to_json(self) -> dict:
        return {"points": list(self.points), "coefficients_rad_per_m": self.coefficients.tolist(),
                "model": "dq_j = c_j * tau_j, tau_j unit-weight gravity torque about joint j (m), base z up"}

    @classmethod
    def from_json(cls, data: dict) -> "GravityCompliance":
        return cls(tuple(data["points"]), torch.tensor(data["coefficients_rad_per_m"], dtype=torch.float64))


class CompliantProblem:
    """A calibration problem over ``[x (P), c (K)]``: geometry plus compliance coefficients.

    Offers what an :class:`~torchcal.identify.base.Identifier` uses (``free``, ``names``,
    ``residuals``, ``jacobian``, ``with_free``).
    """

    def __init__(self, model: ErrorModel, data: Measurements, basis: torch.Tensor, free: torch.Tensor,
                 compliance_columns: list[tuple[int, int]]) -> None:
        self.model, self.data, self.basis, self.free = model, data, basis, free
        self.columns = compliance_columns  # (point, joint) of each compliance parameter
        self.size = model.layout.size
        self.rows_per_pose = 3

    @property
    def names(self) -> list[str]:
        geo = self.model.layout.names
        extra = [f"c_{self.basis_names[k]}{j + 1}" for k, j in self.columns]
        return [geo[i] if i < self.size else extra[i - self.size] for i in self.free.tolist()]

    basis_names: tuple[str, ...] = ()

    def _split(self, xe: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = xe[: self.size]
        c = torch.zeros(self.basis.shape[1], self.basis.shape[2], dtype=xe.dtype)
        for value, (k, j) in zip(xe[self.size :], self.columns):
            c[k, j] = value
        return x, self.data.q + (self.basis * c).sum(1)

    def residuals(self, xe: torch.Tensor) -> torch.Tensor:
        x, q = self._split(xe)
        return (self.data.position - self.model.tcp_position(q, x)).reshape(-1)

    def jacobian(self, xe: torch.Tensor, columns: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        columns = self.free if columns is None else columns
        x, q = self._split(xe)
        layout = self.model.layout
        theta = torch.tensor([layout.index(f"theta{j + 1}") for j in range(self.model.robot.dof)])
        geo = columns[columns < self.size]
        pred, jac = self.model.position_jacobian(q, x, torch.cat([geo, theta]), method="analytic")
        jac_geo, jac_theta = jac[..., : len(geo)], jac[..., len(geo) :]
        parts, g = [], 0
        for col in columns.tolist():
            if col < self.size:
                parts.append(jac_geo[..., g])
                g += 1
            else:
                k, j = self.columns[col - self.size]
                parts.append(jac_theta[..., j] * self.basis[:, k, j : j + 1])
        full = torch.stack(parts, -1)
        r = (self.data.position - pred).reshape(-1)
        return r, -full.reshape(-1, full.shape[-1])

    def with_free(self, free: torch.Tensor) -> "CompliantProblem":
        other = CompliantProblem(self.model, self.data, self.basis, free, self.columns)
        other.basis_names = self.basis_names
        return other


def fit_with_compliance(robot: RobotModel, data: Measurements, geometric, points: tuple[str, ...]):
    """Refine a geometric :class:`~torchcal.identify.calibrate.CalibrationResult` jointly with compliance.

    Returns a result of the same type whose ``compliance`` is set; ``covariance`` is the
    geometric block of the joint covariance (the marginal of the estimated geometry).
    """
    from torchcal.identify.lm import LevenbergMarquardt

    if not points:
        return geometric
    data = data.to("cpu")
    basis = gravity_torque_basis(robot, data.q, points)
    scale = basis.abs().amax(0)  # (K, N)
    cols = [(k, j) for k in range(len(points)) for j in range(robot.dof) if float(scale[k, j]) > _ZERO_COLUMN]
    size = geometric.model.layout.size
    free = torch.cat([geometric.free, torch.arange(size, size + len(cols))])
    problem = CompliantProblem(geometric.model, data, basis, free, cols)
    problem.basis_names = points
    x0 = torch.cat([geometric.x, torch.zeros(len(cols), dtype=torch.float64)])
    sol = LevenbergMarquardt().solve(problem, x0)
    r, jac = problem.jacobian(sol.x)
    cov, sigma = covariance(jac, r)
    n_geo = len(geometric.free)
    coefficients = torch.zeros(len(points), robot.dof, dtype=torch.float64)
    for value, (k, j) in zip(sol.x[size:], cols):
        coefficients[k, j] = value
    x = sol.x[:size].clone()
    reference, x = geometric.model.recentered(x)
    model = ErrorModel(robot, with_orientation=geometric.model.with_orientation,
                       parallel_threshold_deg=geometric.model.parallel_threshold_deg, T_instrument_base=reference)
    notes = list(geometric.notes) + [f"gravity compliance at {'+'.join(points)} identified with the geometry "
                                     f"({len(cols)} coefficients)"]
    return replace(geometric, model=model, x=x, covariance=cov[:n_geo, :n_geo], sigma_residual_m=sigma,
                   notes=notes, compliance=GravityCompliance(points, coefficients))


def predicted_positions(result, q: torch.Tensor) -> torch.Tensor:
    """TCP positions (instrument frame, m) of a result, its compliance included when it has one."""
    compliance = getattr(result, "compliance", None)
    robot = result.model.robot
    q_eff = compliance.effective_joints(robot, q) if compliance is not None else q
    return result.model.tcp_position(q_eff, result.x)


def choose_points_by_cv(robot: RobotModel, data: Measurements, fit_geometry, *, folds: int = 5, seed: int = 0,
                        options: tuple[str, ...] = ("none", "wrist", "elbow+wrist")) -> tuple[str, dict[str, float]]:
    """The point set with the lowest K-fold CV RMS (mm) on ``data``; a simpler set wins ties within 1 %."""
    rng = np.random.default_rng(seed)
    fold = rng.permutation(len(data)) % folds
    scores: dict[str, float] = {}
    for option in options:
        errors = []
        for k in range(folds):
            train, test = data.subset(np.flatnonzero(fold != k)), data.subset(np.flatnonzero(fold == k))
            result = fit_with_compliance(robot, train, fit_geometry(train), POINT_SETS[option])
            errors.append(test.position - predicted_positions(result, test.q))
        scores[option] = float(torch.cat(errors).norm(dim=-1).pow(2).mean().sqrt()) * 1e3
    best = options[0]
    for option in options[1:]:
        if scores[option] < 0.99 * scores[best]:
            best = option
    return best, scores
