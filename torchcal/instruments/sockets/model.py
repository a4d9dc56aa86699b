"""Socket constraints as a least-squares problem over robot parameters and ball-centre points.

Unknowns ``z = [x (robot layout, SI), c_1 .. c_G (3 each, m), k (R N)]``: ``x`` is the
:class:`~torchcal.kinematics.error_model.ErrorModel` vector (per-joint MDH errors, the ball
offset as the tool point in the ``flange`` frame), ``c_g`` the ball-centre point of group ``g``
(one per (placement, socket)) in the robot ``base`` frame. The model's ``T_reference`` is the
identity and ``base_*`` are never free. Optional joint-space terms ``k`` (e.g. gravity compliance,
:mod:`torchcal.identify.compliance`) turn the commanded joints into ``q + sum_r basis_r(q) k_r``
(``basis (n, R, N)``, evaluated at the commanded joints, so the terms are linear in ``k`` and their
columns are ``basis_rj`` times the ``theta_j`` column). ``base_*`` are never free: point constraints cannot see the base frame (moving or
turning it moves every point with it).

Residuals, m:

* per configuration ``i`` in group ``g``: ``p(q_i, x) - c_g`` (3 rows), ``p`` the ball centre
  in ``base``;
* per placement with two sockets ``a, b``: ``w (|c_a - c_b| - D)`` (1 row), ``D`` the fixture's
  socket distance (the scale: without it a smaller robot would fit better), ``w`` its weight.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcal.kinematics.error_model import ErrorModel


def point_names(groups: tuple[tuple[str, int], ...]) -> list[str]:
    """Names of the point unknowns: ``point[<placement>/<socket>]_x`` ..."""
    return [f"point[{p}/{s}]_{c}" for p, s in groups for c in "xyz"]


@dataclass
class SocketsProblem:
    """Residuals and Jacobian of the socket constraints as functions of ``z``.

    Duck-types :class:`~torchcal.identify.problem.CalibrationProblem` (``free``, ``names``,
    ``residuals``, ``jacobian``, ``with_free``) so the project's identifiers solve it.

    Attributes:
        model: error layer with ``T_reference = I`` (ball centre in the robot ``base`` frame).
        q: ``(n, N)`` joints, rad.
        group: ``(n,)`` group index of each configuration.
        groups: ``(placement, socket)`` of each group.
        pairs: ``(G_a, G_b)`` index pairs whose points are ``distance_m`` apart.
        distance_m: socket distance ``D``, m.
        distance_weight: ``w`` of the distance rows (dimensionless).
        free: indices into ``z`` of the estimated unknowns.
    """

    model: ErrorModel
    q: torch.Tensor
    group: torch.Tensor
    groups: tuple[tuple[str, int], ...]
    pairs: torch.Tensor
    distance_m: float
    distance_weight: float
    free: torch.Tensor
    basis: torch.Tensor | None = None
    basis_names: tuple[str, ...] = ()

    @property
    def n_terms(self) -> int:
        return 0 if self.basis is None else self.basis.shape[1] * self.basis.shape[2]

    @property
    def n_robot(self) -> int:
        return self.model.layout.size

    @property
    def n_groups(self) -> int:
        return len(self.groups)

    @property
    def all_names(self) -> list[str]:
        terms = [f"{name}_{j + 1}" for name in self.basis_names for j in range(self.model.robot.dof)]
        return list(self.model.layout.names) + point_names(self.groups) + terms

    @property
    def names(self) -> list[str]:
        names = self.all_names
        return [names[i] for i in self.free.tolist()]

    def split(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(x, points (G, 3))`` of an unknown vector."""
        start = self.n_robot
        return z[:start], z[start : start + 3 * self.n_groups].reshape(self.n_groups, 3)

    def coefficients(self, z: torch.Tensor) -> torch.Tensor:
        """Joint-space coefficients ``(R, N)`` of an unknown vector (empty without a basis)."""
        start = self.n_robot + 3 * self.n_groups
        return z[start:].reshape(-1, self.model.robot.dof)

    def joints(self, z: torch.Tensor) -> torch.Tensor:
        """Joints ``(n, N)`` rad the chain is evaluated at: commanded plus the joint-space terms."""
        q = self.q.to(z)
        if self.basis is None:
            return q
        return q + (self.basis.to(z) * self.coefficients(z)).sum(1)

    def _distance_rows(self, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Distance residuals ``(K,)`` and their unit directions ``(K, 3)`` (from b to a)."""
        if self.pairs.numel() == 0:
            return c.new_zeros(0), c.new_zeros(0, 3)
        diff = c[self.pairs[:, 0]] - c[self.pairs[:, 1]]
        dist = diff.norm(dim=-1)
        return self.distance_weight * (dist - self.distance_m), diff / dist.clamp_min(1e-12).unsqueeze(-1)

    def residuals(self, z: torch.Tensor) -> torch.Tensor:
        """``(3 n + K,)``: point rows (row-major, m) then the weighted distance rows."""
        x, c = self.split(z)
        p = self.model.tcp_position(self.joints(z), x)
        return torch.cat([(p - c[self.group]).reshape(-1), self._distance_rows(c)[0]])

    def jacobian(self, z: torch.Tensor, columns: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals and their Jacobian ``(3 n + K, len(columns))`` with respect to ``z[columns]``."""
        columns = self.free if columns is None else columns
        x, c = self.split(z)
        n, size, g_count = self.q.shape[0], self.n_robot, self.n_groups
        robot_cols = columns[columns < size]
        term_cols = columns[columns >= size + 3 * g_count] - size - 3 * g_count
        dof = self.model.robot.dof
        theta = torch.tensor([self.model.layout.index(f"theta{j + 1}") for j in range(dof)], device=columns.device)
        p, jac_all = self.model.position_jacobian(self.joints(z), x, torch.cat([robot_cols, theta]), method="analytic")
        jac_x, jac_theta = jac_all[..., : robot_cols.numel()], jac_all[..., robot_cols.numel() :]
        dist_r, unit = self._distance_rows(c)
        k = dist_r.numel()
        # d r / d c: -I on the row's own group; +-w u on the distance rows
        jac_c = torch.zeros(3 * n + k, g_count, 3, dtype=z.dtype, device=z.device)
        rows = torch.arange(n, device=z.device)
        for axis in range(3):
            jac_c[3 * rows + axis, self.group.to(z.device), axis] = -1.0
        if k:
            kk = torch.arange(k, device=z.device)
            jac_c[3 * n + kk, self.pairs[:, 0]] = self.distance_weight * unit
            jac_c[3 * n + kk, self.pairs[:, 1]] = -self.distance_weight * unit
        jac_c = jac_c.reshape(3 * n + k, 3 * g_count)
        jac_robot = torch.cat([jac_x.reshape(3 * n, -1), jac_x.new_zeros(k, robot_cols.numel())])
        by_column = torch.empty(3 * n + k, columns.numel(), dtype=z.dtype, device=z.device)
        is_robot = columns < size
        by_column[:, is_robot] = jac_robot
        is_point = ~is_robot & (columns < size + 3 * g_count)
        by_column[:, is_point] = jac_c[:, columns[is_point] - size]
        if term_cols.numel():
            assert self.basis is not None  # term columns exist only with a gravity basis
            rows_, joint = term_cols // dof, term_cols % dof
            cols = jac_theta[..., joint] * self.basis.to(z)[:, rows_, joint].unsqueeze(1)  # (n, 3, T)
            by_column[:, columns >= size + 3 * g_count] = torch.cat([cols.reshape(3 * n, -1), cols.new_zeros(k, cols.shape[-1])])
        r = torch.cat([(p - c[self.group]).reshape(-1), dist_r])
        return r, by_column

    def with_free(self, free: torch.Tensor) -> SocketsProblem:
        return SocketsProblem(self.model, self.q, self.group, self.groups, self.pairs, self.distance_m,
                              self.distance_weight, free, self.basis, self.basis_names)


def group_means(points: torch.Tensor, group: torch.Tensor, n_groups: int) -> torch.Tensor:
    """Mean ``(G, 3)`` of ``points (n, 3)`` per group: each group's least-squares point."""
    sums = torch.zeros(n_groups, 3, dtype=points.dtype, device=points.device).index_add_(0, group.to(points.device), points)
    counts = torch.bincount(group, minlength=n_groups).to(points)
    return sums / counts.unsqueeze(-1)
