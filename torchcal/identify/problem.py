"""The least-squares calibration problem: residuals and Jacobian of measured vs. predicted TCP.

Residual ``r = measured - predicted`` stacked per pose as ``(x, y, z[, wx, wy, wz])`` in the
``instrument`` frame (m; rotation rows in rad times ``orientation_weight_m_per_rad``). With a
``whitening`` matrix per pose (``W_i`` with ``W_i^T W_i`` the inverse covariance of point ``i``,
e.g. multilaterated points) the position rows are ``W_i r_i`` and carry no unit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch

from torchcal.data.measurements import Measurements
from torchcal.identify.series_frames import per_series_registered
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel


class LeastSquaresProblem(Protocol):
    """What the damped Gauss-Newton identifiers need of a problem.

    :class:`CalibrationProblem` is one; the joint-error, tracer-length and profile problems are
    others, with their own parameter vectors.
    """

    @property
    def free(self) -> torch.Tensor:
        """``(K,)`` long indices of the estimated entries of the parameter vector."""
        ...

    @property
    def names(self) -> list[str]:
        """Names of the free parameters, in the order of ``free``."""
        ...

    def residuals(self, x: torch.Tensor) -> torch.Tensor:
        """Residual vector ``(m,)`` at the full parameter vector ``x``."""
        ...

    def jacobian(self, x: torch.Tensor, columns: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals ``(m,)`` and their Jacobian ``(m, K)`` with respect to ``x[columns]`` (default ``free``)."""
        ...


@dataclass
class CalibrationProblem:
    """Model, data and which parameters are free.

    Attributes:
        model: the error layer (its ``T_reference`` is the current instrument frame guess).
        data: validated measurements (SI).
        free: ``(K,)`` long indices of the free parameters in the model's layout.
        use_orientation: include rotation residuals (needs ``data.rotation``).
        orientation_weight_m_per_rad: how many metres of position one radian of orientation
            error is worth in the cost.
        whitening: optional ``(n, 3, 3)`` per-pose whitening of the position residuals, 1/m
            (position data only).
    """

    model: ErrorModel
    data: Measurements
    free: torch.Tensor
    use_orientation: bool = False
    orientation_weight_m_per_rad: float = 1.0
    whitening: torch.Tensor | None = None

    def _whiten(self, r: torch.Tensor) -> torch.Tensor:
        """Apply the per-pose whitening to ``(n, 3, ...)`` position rows."""
        if self.whitening is None:
            return r
        return self.whitening.to(r) @ r

    def _rotation(self) -> torch.Tensor:
        """The measured rotations ``(n, 3, 3)`` the orientation rows compare with."""
        if self.data.rotation is None:
            raise ValueError("orientation residuals need measured rotations (data.rotation is None)")
        return self.data.rotation

    @property
    def rows_per_pose(self) -> int:
        return 6 if self.use_orientation else 3

    @property
    def names(self) -> list[str]:
        all_names = self.model.layout.names
        return [all_names[i] for i in self.free.tolist()]

    def residuals(self, x: torch.Tensor) -> torch.Tensor:
        """``(n * rows_per_pose,)`` residual vector at full parameter vector ``x``."""
        q = self.data.q.to(x)
        if not self.use_orientation:
            r = (self.data.position.to(x) - self.model.tcp_position(q, x)).reshape(-1)
            # pooled series: each series after the first at its own registered frame (identify.series_frames),
            # registered on the points in metres, then whitened
            registered = per_series_registered(self.data, r)[0]
            return self._whiten(registered.reshape(-1, 3, 1)).reshape(-1)
        pose = self.model.tcp_pose(q, x)
        dp = self.data.position.to(x) - pose[..., :3, 3]
        dr = tf.so3_log(self._rotation().to(x) @ pose[..., :3, :3].transpose(-1, -2))
        return torch.cat([dp, dr * self.orientation_weight_m_per_rad], -1).reshape(-1)

    def jacobian(self, x: torch.Tensor, columns: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals ``(m,)`` and their Jacobian ``(m, K)`` with respect to ``x[columns]``.

        Note the sign: ``d r / d x = - d predicted / d x``.
        """
        columns = self.free if columns is None else columns
        q = self.data.q.to(x)
        if not self.use_orientation:
            # the screw-based Jacobian equals the autodiff one (tested) at a fraction of the cost
            pred, jac = self.model.position_jacobian(q, x, columns, method="analytic")
            registered, projected = per_series_registered(self.data, (self.data.position.to(x) - pred).reshape(-1),
                                                          -jac.reshape(-1, jac.shape[-1]))
            assert projected is not None
            n = len(self.data)
            return (self._whiten(registered.reshape(n, 3, 1)).reshape(-1),
                    self._whiten(projected.reshape(n, 3, -1)).reshape(-1, projected.shape[-1]))
        pose, jac = self.model.pose_jacobian(q, x, columns)
        dp = self.data.position.to(x) - pose[..., :3, 3]
        dr = tf.so3_log(self._rotation().to(x) @ pose[..., :3, :3].transpose(-1, -2))
        r = torch.cat([dp, dr * self.orientation_weight_m_per_rad], -1).reshape(-1)
        jac = jac.clone()
        jac[:, 3:] *= self.orientation_weight_m_per_rad
        return r, -jac.reshape(-1, jac.shape[-1])

    def with_free(self, free: torch.Tensor) -> CalibrationProblem:
        return CalibrationProblem(
            self.model, self.data, free, self.use_orientation, self.orientation_weight_m_per_rad, self.whitening
        )
