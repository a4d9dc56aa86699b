"""The differentiable error layer: nominal robot + calibration parameters -> TCP pose.

Parameters live in one flat float64 vector ``x`` (SI units) whose layout is
:class:`ParameterLayout`:

* per joint ``i`` (MDH row ``i``): ``alpha{i}, a{i}, beta{i}, theta{i}, d{i}``, absolute values
  (rad, m) of ``alpha_(i-1), a_(i-1), beta_(i-1), theta_i`` (zero offset) and ``d_i``;
* ``base_x, base_y, base_z`` (m) and ``base_rx, base_ry, base_rz`` (rotation vector, rad): a
  correction applied on the right of a reference ``T_instrument_base`` found by closed-form
  registration, so the vector stays small and the rotation never nears the log's singularity;
* ``tool_x, tool_y, tool_z`` (m): TCP / reflector in the ``flange`` frame, and
  ``tool_rx, tool_ry, tool_rz`` (rotation vector, rad): tool orientation, used only with
  orientation data.

Which of them are free is the *active* mask. Hayati rule: where the nominal axes ``i-1`` and
``i`` are within ``parallel_threshold_deg`` of parallel (``|sin alpha_(i-1)| < sin threshold``),
``beta{i}`` is free and ``d{i}`` is fixed, because a small tilt of nearly parallel axes would
otherwise be explained by an arbitrarily large ``d``; elsewhere ``beta{i}`` is fixed at 0.

All functions are batched over leading dimensions and differentiable with respect to ``x``,
which may be shared ``(P,)`` or per pose ``(..., P)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.mdh import chain_point, chain_transforms
from torchcal.kinematics.param_jacobian import tcp_position_jacobian
from torchcal.kinematics.robot import RobotModel

JOINT_FIELDS = ("alpha", "a", "beta", "theta", "d")
BASE_FIELDS = ("base_x", "base_y", "base_z", "base_rx", "base_ry", "base_rz")
TOOL_FIELDS = ("tool_x", "tool_y", "tool_z", "tool_rx", "tool_ry", "tool_rz")
DEFAULT_PARALLEL_THRESHOLD_DEG = 2.0


@dataclass(frozen=True)
class ParameterLayout:
    """Names and positions of the calibration parameters of an ``n_joints`` robot."""

    n_joints: int

    @property
    def names(self) -> tuple[str, ...]:
        joint = tuple(f"{f}{i}" for i in range(1, self.n_joints + 1) for f in JOINT_FIELDS)
        return joint + BASE_FIELDS + TOOL_FIELDS

    @property
    def size(self) -> int:
        return 5 * self.n_joints + 12

    @property
    def table_slice(self) -> slice:
        return slice(0, 5 * self.n_joints)

    @property
    def base_slice(self) -> slice:
        return slice(5 * self.n_joints, 5 * self.n_joints + 6)

    @property
    def tool_slice(self) -> slice:
        return slice(5 * self.n_joints + 6, 5 * self.n_joints + 12)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def is_angle(self) -> torch.Tensor:
        """Boolean mask of parameters in rad (the rest are in m)."""
        flags = [f in ("alpha", "beta", "theta") for _ in range(self.n_joints) for f in JOINT_FIELDS]
        flags += [False, False, False, True, True, True] * 2
        return torch.tensor(flags)

    def unit_scale(self) -> torch.Tensor:
        """Factor from SI to report units (mm for lengths, deg for angles)."""
        return torch.where(self.is_angle(), 180.0 / math.pi, 1e3).to(torch.float64)


class ErrorModel:
    """Nominal robot plus the calibration parameters that a measurement can correct.

    Args:
        robot: the nominal :class:`RobotModel`.
        with_orientation: free the tool rotation (only meaningful with orientation data).
        parallel_threshold_deg: Hayati switch threshold (see module docstring).
        T_instrument_base: reference ``(4, 4)`` instrument-from-base transform (identity if the
            measurements are in the robot ``base`` frame).
        device: where tensors live (CPU by default).
    """

    def __init__(
        self,
        robot: RobotModel,
        *,
        with_orientation: bool = False,
        parallel_threshold_deg: float = DEFAULT_PARALLEL_THRESHOLD_DEG,
        T_instrument_base: torch.Tensor | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        self.robot = robot
        self.device = torch.device(device)
        self.layout = ParameterLayout(robot.dof)
        self.parallel_threshold_deg = float(parallel_threshold_deg)
        self.with_orientation = with_orientation
        self.T_base_0 = robot.T_base_0.to(self.device, torch.float64)
        self.T_n_flange = robot.T_n_flange.to(self.device, torch.float64)
        ref = torch.eye(4, dtype=torch.float64) if T_instrument_base is None else T_instrument_base
        self.T_reference = ref.to(self.device, torch.float64)
        self.parallel_joints = self._parallel_joints()

    # ------------------------------------------------------------------------- parameters

    def _parallel_joints(self) -> tuple[int, ...]:
        """1-based rows whose axis is nearly parallel to the previous one (Hayati beta rows)."""
        limit = math.sin(math.radians(self.parallel_threshold_deg))
        # Row 1's "previous axis" is the base z: the base frame absorbs it.
        return tuple(i + 1 for i in range(1, self.robot.dof) if abs(math.sin(float(self.robot.table[i, 0]))) < limit)

    def nominal_vector(self) -> torch.Tensor:
        """``x`` of the nominal robot: datasheet table, zero base correction, nominal tool."""
        x = torch.zeros(self.layout.size, dtype=torch.float64, device=self.device)
        x[self.layout.table_slice] = self.robot.table.reshape(-1).to(self.device)
        x[self.layout.tool_slice][:3] = self.robot.tool.to(self.device)
        tool = x[self.layout.tool_slice]
        tool[:3] = self.robot.tool.to(self.device)
        return x

    def default_active(self) -> torch.Tensor:
        """Free parameters before identifiability analysis (Hayati rule applied)."""
        active = torch.zeros(self.layout.size, dtype=torch.bool)
        for i in range(1, self.robot.dof + 1):
            for field in ("alpha", "a", "theta"):
                active[self.layout.index(f"{field}{i}")] = True
            hayati = i in self.parallel_joints
            active[self.layout.index(f"beta{i}")] = hayati
            active[self.layout.index(f"d{i}")] = not hayati
        active[self.layout.base_slice] = True
        active[self.layout.tool_slice.start : self.layout.tool_slice.start + 3] = True
        if self.with_orientation:
            active[self.layout.tool_slice.start + 3 : self.layout.tool_slice.stop] = True
        return active

    def table(self, x: torch.Tensor) -> torch.Tensor:
        """MDH rows ``(..., N, 5)`` of parameter vector(s) ``x``."""
        return x[..., self.layout.table_slice].reshape(*x.shape[:-1], self.robot.dof, 5)

    def instrument_from_base(self, x: torch.Tensor) -> torch.Tensor:
        """``T_instrument_base`` ``(..., 4, 4)``."""
        base = x[..., self.layout.base_slice]
        correction = tf.homogeneous(tf.so3_exp(base[..., 3:]), base[..., :3])
        return self.T_reference.to(x) @ correction

    def flange_from_tool(self, x: torch.Tensor) -> torch.Tensor:
        """``T_flange_tool`` ``(..., 4, 4)``."""
        tool = x[..., self.layout.tool_slice]
        return tf.homogeneous(tf.so3_exp(tool[..., 3:]), tool[..., :3])

    def recentered(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Fold the base correction into the reference: returns ``(new_reference, x_with_zero_base)``."""
        reference = self.instrument_from_base(x)
        x = x.clone()
        x[self.layout.base_slice] = 0.0
        return reference, x

    # ------------------------------------------------------------------------ kinematics

    def base_flange_pose(self, q: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``T_base_flange`` ``(..., 4, 4)`` for joints ``q`` ``(..., N)`` rad."""
        rot, pos = chain_transforms(q, self.table(x))
        return self.T_base_0.to(q) @ tf.homogeneous(rot, pos) @ self.T_n_flange.to(q)

    def tcp_pose(self, q: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``T_instrument_tool`` ``(..., 4, 4)``: the TCP pose in the instrument frame."""
        return self.instrument_from_base(x) @ self.base_flange_pose(q, x) @ self.flange_from_tool(x)

    def instrument_from_0(self, x: torch.Tensor) -> torch.Tensor:
        """``T_instrument_0`` ``(..., 4, 4)``: MDH frame 0 in the instrument frame."""
        return self.instrument_from_base(x) @ self.T_base_0.to(x)

    def tool_in_n(self, x: torch.Tensor) -> torch.Tensor:
        """TCP position ``(..., 3)`` in MDH frame ``N``, m (tool point through ``T_n_flange``)."""
        tn = self.T_n_flange.to(x)
        tool = x[..., self.layout.tool_slice.start : self.layout.tool_slice.start + 3]
        return tool @ tn[:3, :3].T + tn[:3, 3]

    def tcp_position(self, q: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """TCP position ``(..., 3)`` in the instrument frame, m.

        The hot path of identification: the TCP point is carried from frame ``N`` down the chain
        with scalar-array algebra (:func:`torchcal.kinematics.mdh.chain_point`); no 4x4 or 3x3
        product per pose.
        """
        world = self.instrument_from_0(x)
        return chain_point(
            q, self.table(x), self.tool_in_n(x), r_start=world[..., :3, :3], p_start=world[..., :3, 3]
        )

    def position_jacobian(
        self,
        q: torch.Tensor,
        x: torch.Tensor,
        columns: torch.Tensor | None = None,
        *,
        method: str = "autodiff",
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """TCP positions and their Jacobian with respect to ``x``.

        Args:
            q: ``(B, N)`` joint angles, rad.
            x: ``(P,)`` parameter vector.
            columns: indices of the parameters to differentiate (default: all).
            method: ``"autodiff"`` (reverse-mode autodiff through :meth:`tcp_position`, the
                reference) or ``"analytic"`` (screw-form columns from one forward pass, see
                :mod:`torchcal.kinematics.param_jacobian`; same values to rounding, 4x to 50x
                faster in docs/bench_kinematics.md, the choice for identification loops).

        Returns:
            ``(p, J)``: ``p (B, 3)`` in m, ``J (B, 3, K)`` in m per parameter unit.
        """
        if method == "analytic":
            return self.position_jacobian_analytic(q, x, columns)
        if method != "autodiff":
            raise ModelError(f"position_jacobian method must be 'autodiff' or 'analytic', got {method!r}")
        columns = torch.arange(x.shape[-1], device=x.device) if columns is None else columns
        batch = q.shape[0]
        # One parameter copy per pose makes every pose's gradient its own row: three
        # reverse passes (one per coordinate) give the whole (B, 3, P) Jacobian.
        per_pose = x.detach().expand(batch, -1).clone().requires_grad_(True)
        with torch.enable_grad():
            p = self.tcp_position(q, per_pose)
            rows = [
                torch.autograd.grad(p[:, k].sum(), per_pose, retain_graph=k < 2)[0][:, columns]
                for k in range(3)
            ]
        return p.detach(), torch.stack(rows, 1)

    def position_jacobian_analytic(
        self, q: torch.Tensor, x: torch.Tensor, columns: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """As :meth:`position_jacobian` with ``method="analytic"``: ``(p (B, 3), J (B, 3, K))``, m."""
        return tcp_position_jacobian(self, q, x, columns)

    def pose_jacobian(
        self, q: torch.Tensor, x: torch.Tensor, columns: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """TCP pose as ``[p (3), rotation vector relative to the current pose (3)]`` and Jacobian.

        Returns ``(T, J)`` with ``T (B, 4, 4)`` and ``J (B, 6, K)``; the rotation rows are the
        instrument-frame small-angle rotation of the TCP per parameter.
        """
        columns = torch.arange(x.shape[-1], device=x.device) if columns is None else columns
        batch = q.shape[0]
        with torch.no_grad():
            current = self.tcp_pose(q, x)
        r_now_t = current[..., :3, :3].transpose(-1, -2)
        free = x[columns].expand(batch, -1).clone()

        def pose_vector(free_values: torch.Tensor) -> torch.Tensor:
            full = x.expand(batch, -1).clone()
            full[:, columns] = free_values
            pose = self.tcp_pose(q, full)
            delta = pose[..., :3, :3] @ r_now_t
            # first-order rotation vector of delta (exact derivative at delta = I)
            w = 0.5 * torch.stack(
                [delta[..., 2, 1] - delta[..., 1, 2], delta[..., 0, 2] - delta[..., 2, 0], delta[..., 1, 0] - delta[..., 0, 1]],
                -1,
            )
            return torch.cat([pose[..., :3, 3], w], -1)

        with torch.enable_grad():
            vjp_fn = torch.func.vjp(pose_vector, free)[1]  # (value, vjp function): no has_aux
            basis = torch.eye(6, dtype=x.dtype, device=x.device)
            (jac,) = torch.vmap(vjp_fn)(basis[:, None, :].expand(6, batch, 6))
        return current, jac.permute(1, 0, 2).detach()
