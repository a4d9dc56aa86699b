"""The laser tracker: 3-D reflector points in the tracker's own (unknown, rigid) frame."""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

import torch

from torchcal.errors import DataError
from torchcal.kinematics.transforms import rigid_registration, so3_exp, so3_log
from torchcal.measure.base import Instrument, joint_columns

_XYZ = ("x", "y", "z")


class TrackerInstrument(Instrument):
    """Laser tracker measuring points ``p_instrument = R p + t`` with isotropic Gaussian noise.

    Nuisance parameters: ``[rotvec (3, rad), t (3, m)]`` of ``T_instrument_base``, i.e. the tracker
    frame relative to the frame the points are predicted in.

    Args:
        sigma_m: standard deviation of every coordinate, m.
        T_instrument_base: ``(4, 4)`` true frame used by :meth:`simulate` (identity by default).
    """

    name: ClassVar[str] = "tracker"

    def __init__(self, sigma_m: float = 20e-6, T_instrument_base: torch.Tensor | None = None) -> None:
        if not sigma_m > 0:
            raise ValueError(f"sigma_m must be positive, got {sigma_m}")
        self.sigma_m = float(sigma_m)
        self.T_instrument_base = (
            torch.eye(4, dtype=torch.float64) if T_instrument_base is None else T_instrument_base.to(torch.float64)
        )

    def columns(self, n_joints: int) -> list[str]:
        return joint_columns(n_joints) + list(_XYZ)

    def simulate(self, true_points_m: torch.Tensor, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        t = self.T_instrument_base.to(true_points_m)
        p = true_points_m @ t[:3, :3].T + t[:3, 3]
        noise = torch.randn(p.shape, generator=generator, dtype=p.dtype, device=p.device) * self.sigma_m
        return dict(zip(_XYZ, (p + noise).unbind(-1)))

    @staticmethod
    def _points(measured: Mapping[str, torch.Tensor]) -> torch.Tensor:
        missing = [c for c in _XYZ if c not in measured]
        if missing:
            raise DataError(f"tracker data needs columns x, y, z; missing {', '.join(missing)}", column=missing[0])
        return torch.stack([torch.as_tensor(measured[c], dtype=torch.float64) for c in _XYZ], -1)

    def initial_params(self, points_m: torch.Tensor, measured: Mapping[str, torch.Tensor]) -> torch.Tensor:
        meas = self._points(measured).to(points_m)
        ok = torch.isfinite(meas).all(-1)
        if int(ok.sum()) < 3:
            raise DataError(f"the tracker frame needs at least 3 measured points, got {int(ok.sum())}")
        t = rigid_registration(points_m[ok], meas[ok])
        return torch.cat([so3_log(t[:3, :3]), t[:3, 3]])

    def residuals(
        self, points_m: torch.Tensor, measured: Mapping[str, torch.Tensor], params: torch.Tensor
    ) -> torch.Tensor:
        meas = self._points(measured).to(points_m)
        ok = torch.isfinite(meas).all(-1)
        pred = points_m @ so3_exp(params[:3]).T + params[3:6]
        return ((pred - meas)[ok] / self.sigma_m).reshape(-1)
