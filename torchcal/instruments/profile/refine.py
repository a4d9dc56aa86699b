"""Joint refinement of the profile-sensor extrinsics and the target placements.

Unknowns (SI): the sensor rotation as a small rotation vector ``delta`` in the ``flange`` frame
(``R = exp(delta) R_0``), the translation ``t`` (m), and per placement a tangent rotation
``(e1, e2)`` of its unit normal (``n = exp(e1 b1 + e2 b2) n_0``) and its offset ``c`` (m).
Residuals are the signed point-to-plane distances ``n . p - c`` (m) of every profile point,
with the flange poses fixed (nominal or calibrated robot). The problem is solved by the
project's Levenberg-Marquardt (:class:`torchcal.identify.lm.LevenbergMarquardt`), which needs
only ``free``, ``names``, ``residuals(x)`` and ``jacobian(x)``; the Jacobian is exact (forward-mode
autodiff, ``6 + 3 P`` columns). After convergence the references are moved to the solution, so
the covariance ``s^2 (J^T J)^-1`` is that of small flange-frame angles and of ``t``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.core.errors import DataError
from torchcal.identify.lm import LevenbergMarquardt
from torchcal.instruments.profile.data import ProfileData
from torchcal.instruments.profile.model import base_points, orthogonal_basis, plane_distances
from torchcal.kinematics import transforms as tf

RANK_RATIO = 1e-8
#: A sensor rotation known no better than this (1 sigma, deg, about any flange axis) is no pose
#: to write: the data (wrong units, scans from other poses) do not determine it.
MAX_SIGMA_ROTATION_DEG = 10.0


@dataclass
class ProfileProblem:
    """Point-to-plane least squares in the interface the project's identifiers use.

    Attributes:
        data: profile scans (SI).
        T_base_flange: ``(S, 4, 4)`` flange pose per scan.
        R_ref: ``(3, 3)`` reference rotation; ``x[:3]`` rotates it in the flange frame.
        normals_ref: ``(P, 3)`` reference plane normals (``base``).
    """

    data: ProfileData
    T_base_flange: torch.Tensor
    R_ref: torch.Tensor
    normals_ref: torch.Tensor

    def __post_init__(self) -> None:
        self.bases = torch.stack([orthogonal_basis(n) for n in self.normals_ref])  # (P, 2, 3)
        self.point_plane = self.data.point_plane()
        self.free = torch.arange(6 + 3 * self.data.n_planes)

    @property
    def names(self) -> list[str]:
        names = ["rot_x", "rot_y", "rot_z", "t_x", "t_y", "t_z"]
        for label in self.data.plane_labels:
            names += [f"plane{label}_tilt1", f"plane{label}_tilt2", f"plane{label}_offset"]
        return names

    def initial(self, t: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
        """``x`` at the references: zero rotations, ``t`` (m) and plane ``offsets`` (m)."""
        x = torch.zeros(6 + 3 * self.data.n_planes, dtype=torch.float64, device=t.device)
        x[3:6] = t
        x[8::3] = offsets
        return x

    def unpack(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``R (3, 3)``, ``t (3,)``, normals ``(P, 3)``, offsets ``(P,)`` of ``x``."""
        R = tf.so3_exp(x[:3]) @ self.R_ref
        planes = x[6:].reshape(-1, 3)
        tilt = planes[:, 0:1] * self.bases[:, 0] + planes[:, 1:2] * self.bases[:, 1]
        normals = (tf.so3_exp(tilt) @ self.normals_ref.unsqueeze(-1)).squeeze(-1)
        return R, x[3:6], normals, planes[:, 2]

    def residuals(self, x: torch.Tensor) -> torch.Tensor:
        """Signed point-to-plane distances ``(K,)``, m."""
        R, t, normals, offsets = self.unpack(x)
        points = base_points(self.T_base_flange, self.data.point_scan, self.data.uw, R, t)
        return plane_distances(points, self.point_plane, normals, offsets)

    def jacobian(self, x: torch.Tensor, columns: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Residuals ``(K,)`` and their exact Jacobian ``(K, len(columns))``."""
        jac = torch.func.jacfwd(self.residuals)(x)
        cols = self.free if columns is None else columns
        return self.residuals(x), jac[:, cols]

    def recentred(self, x: torch.Tensor) -> tuple[ProfileProblem, torch.Tensor]:
        """The same problem with references moved to ``x``, and the equivalent ``x`` (zero angles)."""
        R, t, normals, offsets = self.unpack(x)
        problem = ProfileProblem(self.data, self.T_base_flange, R, normals)
        return problem, problem.initial(t, offsets)


@dataclass
class RefineResult:
    """Refined extrinsics, placements and their uncertainty.

    Attributes:
        R, t: ``R_flange_sensor`` ``(3, 3)`` and ``t_flange_sensor`` ``(3,)``, m.
        normals / offsets: ``(P, 3)`` and ``(P,)`` placements in ``base`` (m).
        covariance: ``(6+3P, 6+3P)`` in SI of ``[flange-frame angles (rad), t (m), per plane
            tilt1, tilt2 (rad), offset (m)]``.
        sigma_residual: residual standard deviation, m.
        residuals: ``(K,)`` final point-to-plane distances, m.
        iterations / converged / message / history: solver report.
    """

    R: torch.Tensor
    t: torch.Tensor
    normals: torch.Tensor
    offsets: torch.Tensor
    covariance: torch.Tensor
    sigma_residual: float
    residuals: torch.Tensor
    iterations: int
    converged: bool
    message: str
    history: list[float]

    @property
    def sigma_rotation_deg(self) -> list[float]:
        return [math.degrees(v) for v in self.covariance.diagonal()[:3].clamp_min(0).sqrt().tolist()]

    @property
    def sigma_t_mm(self) -> list[float]:
        return [v * 1e3 for v in self.covariance.diagonal()[3:6].clamp_min(0).sqrt().tolist()]


def _check_rank(problem: ProfileProblem, jac: torch.Tensor) -> None:
    """A rank-deficient Jacobian names the parameters of its weakest direction."""
    scale = jac.norm(dim=0).clamp_min(1e-300)
    _, s, vh = torch.linalg.svd(jac / scale, full_matrices=False)
    if float(s[-1]) > RANK_RATIO * float(s[0]):
        return
    weak = vh[-1].abs()
    names = [problem.names[i] for i in weak.argsort(descending=True)[:3].tolist() if float(weak[i]) > 0.1]
    raise DataError(
        f"the scans do not determine {', '.join(names)} (the point-to-plane problem is rank deficient); "
        "add placements, translations or rotations about other axes",
        path=problem.data.path,
    )


def _check_sigma(problem: ProfileProblem, result: RefineResult) -> None:
    """Refuse a solution whose rotation sigmas exceed :data:`MAX_SIGMA_ROTATION_DEG`, naming them."""
    sigma = result.sigma_rotation_deg
    loose = [f"{problem.names[i]} +-{v:.3g} deg" for i, v in enumerate(sigma) if not v <= MAX_SIGMA_ROTATION_DEG]
    if not loose:
        return
    raise DataError(
        f"the scans determine the sensor rotation only to {', '.join(loose)} (1 sigma, more than "
        f"{MAX_SIGMA_ROTATION_DEG:g} deg) with a point-to-plane RMS of {result.sigma_residual * 1e3:.3g} mm: "
        "check the u, w unit (length_unit) and that every scan's joints are the pose it was taken at",
        path=problem.data.path,
    )


def refine(
    data: ProfileData,
    T_base_flange: torch.Tensor,
    R0: torch.Tensor,
    t0: torch.Tensor,
    normals0: torch.Tensor,
    offsets0: torch.Tensor,
    *,
    max_iterations: int = 100,
) -> RefineResult:
    """Levenberg-Marquardt on all points, from a start (closed form or search), with covariance.

    Raises:
        DataError: the Jacobian at the solution is rank deficient, or a rotation sigma exceeds
            :data:`MAX_SIGMA_ROTATION_DEG` (names the parameters).
    """
    problem = ProfileProblem(data, T_base_flange.to(data.uw), R0.to(data.uw), normals0.to(data.uw))
    x0 = problem.initial(t0.to(data.uw), offsets0.to(data.uw))
    solver = LevenbergMarquardt(max_iterations=max_iterations, ftol=1e-14, xtol=1e-14, gtol=1e-12)
    sol = solver.solve(problem, x0)
    problem, x = problem.recentred(sol.x)
    r, jac = problem.jacobian(x)
    _check_rank(problem, jac)
    dof = max(r.numel() - jac.shape[1], 1)
    s2 = float(r @ r) / dof
    covariance = s2 * torch.linalg.inv(jac.T @ jac)
    R, t, normals, offsets = problem.unpack(x)
    result = RefineResult(
        R=R, t=t, normals=normals, offsets=offsets, covariance=covariance, sigma_residual=math.sqrt(s2),
        residuals=r, iterations=sol.iterations, converged=sol.converged, message=sol.message, history=sol.history,
    )
    _check_sigma(problem, result)
    return result
