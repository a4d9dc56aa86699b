"""Gravity-induced joint compliance identified with the geometry, from positions alone.

Model. A point weight at ``p`` loads joint ``j`` (axis ``z_j`` through ``o_j``) with the torque
``tau_j = z_j . ((p - o_j) x (-e_z))`` per unit weight (m; ``base`` z up), and the joint gives
way by ``dq_j = c_j tau_j``. Points: ``tcp`` (the nominal TCP: wrist, tool and payload, beyond
every joint), ``elbow`` (origin of MDH frame 3, beyond joints 1 and 2 only: the upper arm) and
``forearm`` (origin of MDH frame 5, the wrist centre of a spherical wrist, loading joints 1 to 3:
the forearm and the wrist motors it carries). Without ``forearm`` the forearm's weight can only be
taken by the ``tcp`` point, whose lever turns with the wrist while the forearm's does not. The coefficient
``c`` (rad per metre of unit-weight lever, i.e. weight over stiffness) is estimated; torques are
evaluated on the *nominal* chain, so ``dq`` is linear in ``c`` and the TCP displacement per
coefficient is ``tau_j`` times the ``theta_j`` column of the position Jacobian.

Nonlinear compliance. A joint whose stiffness softens or hardens with the load (a strain-wave
gear stiffens with torque; bearing play softens it near zero) gives way by a nonlinear function of
the torque: ``cubic`` adds the basis function ``tau_j^3`` (m^3) of the ``tcp`` torque, so
``dq_j = c_j tau_j + c3_j tau_j^3``, still linear in the coefficients.

Why. Cable-driven or light arms (a WAM, a UR) sag measurably under their own weight; a
geometric model cannot express a deflection that changes with the load direction, so it leaves
it in the residual. Which points to use is a model choice made by K-fold cross-validation on the
training poses (``auto``), never on a test set. The joint fit with the geometry is
:mod:`torchcal.identify.joint_fit`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.mdh import chain_frames
from torchcal.kinematics.robot import RobotModel

POINT_SETS: dict[str, tuple[str, ...]] = {"none": (), "wrist": ("tcp",), "elbow+wrist": ("elbow", "tcp"),
                                          "elbow+wrist+cubic": ("elbow", "tcp", "tcp3"),
                                          "elbow+forearm+wrist": ("elbow", "forearm", "tcp")}
#: Basis functions of the gravity torque: the point whose torque it takes and the power.
POINT_FUNCTIONS: dict[str, tuple[str, int]] = {"tcp": ("tcp", 1), "elbow": ("elbow", 1), "tcp3": ("tcp", 3),
                                                "forearm": ("forearm", 1)}
ELBOW_FRAME = 3  # MDH frame whose origin stands for the upper-arm mass
FOREARM_FRAME = 5  # MDH frame whose origin (the wrist centre of a spherical wrist) stands for the forearm mass
#: MDH frame whose origin stands for a point mass, and how many joints (from the base) its weight loads.
FRAME_POINTS: dict[str, tuple[int, int]] = {"elbow": (ELBOW_FRAME, ELBOW_FRAME - 1), "forearm": (FOREARM_FRAME, ELBOW_FRAME)}
_ZERO_COLUMN = 1e-9  # a basis column below this norm (m) has no effect: joint axis along gravity


def gravity_torque_basis(robot: RobotModel, q: torch.Tensor, points: tuple[str, ...],
                         tcp_point: torch.Tensor | None = None) -> torch.Tensor:
    """Unit-weight gravity torques ``(B, len(points), N)`` in m about each joint, nominal chain, ``base`` z up.

    ``tcp_point``: where the ``tcp`` point lies in the robot's flange frame (m; default: the robot's
    tool point), so that a view ending in another TCP keeps the point the terms were fitted at.
    """
    model = ErrorModel(robot)
    x = model.nominal_vector()
    frames = chain_frames(q, model.table(x), r_start=model.T_base_0[:3, :3].to(q), p_start=model.T_base_0[:3, 3].to(q))
    axes, origins = frames.stacked("z"), frames.stacked("o")  # (B, N, 3), base frame
    n = robot.dof
    down = torch.tensor([0.0, 0.0, -1.0], dtype=q.dtype, device=q.device)
    out = []
    for label in points:
        if label not in POINT_FUNCTIONS:
            raise ValueError(f"unknown gravity point '{label}'; choose one of {sorted(POINT_FUNCTIONS)}")
        name, power = POINT_FUNCTIONS[label]
        if name == "tcp":
            beyond = torch.ones(n, dtype=q.dtype)
            if tcp_point is None:
                point = model.tcp_position(q, x)
            else:
                flange = robot.flange_pose(q)
                point = flange[..., :3, :3] @ tcp_point.to(q) + flange[..., :3, 3]
        else:
            frame, loaded = FRAME_POINTS[name]
            point = origins[:, min(frame, n) - 1]
            beyond = torch.tensor([1.0 if j < loaded else 0.0 for j in range(n)], dtype=q.dtype)
        lever = point[:, None, :] - origins
        tau = (torch.linalg.cross(lever, down.expand_as(lever), dim=-1) * axes).sum(-1)
        out.append(tau**power * beyond.to(q.device))
    return torch.stack(out, 1) if out else q.new_zeros(q.shape[0], 0, n)


@dataclass(frozen=True)
class GravityCompliance:
    """Identified compliance: ``points`` and ``coefficients (len(points), N)`` in rad/m (``tcp3``: rad/m^3)."""

    points: tuple[str, ...]
    coefficients: torch.Tensor
    #: The ``tcp`` point in the robot's flange frame (m), where a view of the model ends in another TCP
    #: than the one fitted (:func:`~torchcal.compensate.production_tcp.production_view`); ``None``: the
    #: robot's tool point, as fitted.
    tcp_point: torch.Tensor | None = None

    def deflection(self, robot: RobotModel, q: torch.Tensor) -> torch.Tensor:
        """Joint deflection ``(B, N)`` rad at commanded joints ``q`` ``(B, N)`` rad."""
        basis = gravity_torque_basis(robot, q, self.points, self.tcp_point)
        return (basis * self.coefficients.to(q)).sum(1)

    def effective_joints(self, robot: RobotModel, q: torch.Tensor) -> torch.Tensor:
        """The joint angles the arm actually takes under its own weight, rad."""
        return q + self.deflection(robot, q)

    def to_json(self) -> dict:
        out = {"points": list(self.points), "coefficients_rad_per_m": self.coefficients.tolist(),
               "model": "dq_j = sum_k c_kj * f_k(tau_j), tau_j unit-weight gravity torque about joint j (m), base z up; "
                        "point tcp3: the tcp torque cubed (m^3)"}
        if self.tcp_point is not None:
            out["tcp_point_m"] = self.tcp_point.tolist()
        return out

    @classmethod
    def from_json(cls, data: dict) -> GravityCompliance:
        point = data.get("tcp_point_m")
        return cls(tuple(data["points"]), torch.tensor(data["coefficients_rad_per_m"], dtype=torch.float64),
                   None if point is None else torch.tensor(point, dtype=torch.float64))
