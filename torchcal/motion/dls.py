"""Damped least-squares (DLS) inverse of a Jacobian with adaptive damping.

``J* = J^T (J J^T + a^2 I)^-1``, computed from the SVD ``J = U S V^T`` as
``V diag(s_i / (s_i^2 + a^2)) U^T`` (the same matrix, but it also yields ``sigma_min`` and stays
finite at an exact singularity).

Adaptive damping (Nakamura & Hanafusa 1986; Maciejewski & Klein 1988): the damping is zero
while the smallest singular value is at least ``eps`` and rises smoothly as it drops below::

    a^2 = 0                                   if sigma_min >= eps
    a^2 = a_max^2 * (1 - (sigma_min/eps)^2)   otherwise

* ``eps`` bounds the *singular neighbourhood* ``sigma_min < eps``. Outside it ``J* = J^+`` exactly,
  so tracking is as accurate as the undamped inverse; inside it the solution trades accuracy in
  the near-singular direction for bounded joint speed.
* ``a_max`` caps the gain of the inverse: ``s / (s^2 + a^2)`` is at most ``1 / (2 a)`` whatever
  ``sigma_min`` is, so ``|q_dot| <= |x_dot| / (2 a_max)`` in the worst direction at ``sigma = 0``.

Singular values carry the Jacobian's mixed units (m/rad for the linear rows, rad/rad for the
angular ones); the wrist singularity's vanishing direction is mostly angular, so ``eps`` and
``a_max`` are effectively dimensionless for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchcal.core.errors import ModelError

DEFAULT_EPS = 0.04
DEFAULT_A_MAX = 0.06


@dataclass(frozen=True)
class DLSInverse:
    """A batched Jacobian inverse and the singular-value diagnostics that produced it.

    Attributes:
        inverse: ``(..., N, M)`` inverse of the ``(..., M, N)`` Jacobian.
        sigma: ``(..., min(M, N))`` singular values, descending.
        sigma_min: ``(...)`` smallest singular value.
        damping_sq: ``(...)`` damping ``a^2`` that was applied (0 outside the neighbourhood).
    """

    inverse: torch.Tensor
    sigma: torch.Tensor
    sigma_min: torch.Tensor
    damping_sq: torch.Tensor

    @property
    def manipulability(self) -> torch.Tensor:
        """Yoshikawa manipulability ``sqrt(det(J J^T)) = prod(sigma)`` ``(...)``."""
        return self.sigma.prod(-1)


def adaptive_damping(sigma_min: torch.Tensor, eps: float = DEFAULT_EPS, a_max: float = DEFAULT_A_MAX) -> torch.Tensor:
    """Damping ``a^2`` ``(...)`` for smallest singular values ``sigma_min`` ``(...)``.

    Zero for ``sigma_min >= eps``, ``a_max^2`` at ``sigma_min = 0``, continuous in between (so the
    inverse, and with it the joint velocity, is continuous across the neighbourhood's edge).
    """
    if eps <= 0.0 or a_max < 0.0:
        raise ModelError(f"adaptive damping needs eps > 0 and a_max >= 0, got eps={eps}, a_max={a_max}")
    ratio = (sigma_min / eps).clamp(max=1.0)
    return a_max**2 * (1.0 - ratio**2)


def _filtered_inverse(
    jac: torch.Tensor, damping_sq=None, eps: float = DEFAULT_EPS, a_max: float = DEFAULT_A_MAX, selective: bool = False
) -> DLSInverse:
    """SVD-filtered inverse; ``damping_sq=None`` means adaptive damping from ``sigma_min``."""
    u, s, vh = torch.linalg.svd(jac, full_matrices=False)
    if damping_sq is None:
        a2 = adaptive_damping(s[..., -1], eps, a_max)
        per_value = adaptive_damping(s, eps, a_max) if selective else a2.unsqueeze(-1)
    else:
        a2 = torch.as_tensor(damping_sq, dtype=jac.dtype, device=jac.device).expand(s.shape[:-1])
        per_value = a2.unsqueeze(-1)
    denom = s**2 + per_value
    # s / (s^2 + a^2); an exactly zero singular value without damping maps to 0 (pinv convention)
    gain = torch.where(denom > 0, s / denom.clamp_min(torch.finfo(s.dtype).tiny), torch.zeros_like(s))
    inverse = vh.transpose(-1, -2) @ (gain.unsqueeze(-1) * u.transpose(-1, -2))
    return DLSInverse(inverse=inverse, sigma=s, sigma_min=s[..., -1], damping_sq=a2)


def dls_inverse(
    jac: torch.Tensor, eps: float = DEFAULT_EPS, a_max: float = DEFAULT_A_MAX, selective: bool = False
) -> DLSInverse:
    """Adaptive-damping DLS inverse of ``jac`` ``(..., M, N)`` (see module docstring).

    ``selective=True`` damps each singular value by the same law of its own value instead of
    all of them by the law of ``sigma_min`` (numerical filtering): directions far from singular
    keep the exact inverse inside the neighbourhood too.
    """
    return _filtered_inverse(jac, None, eps, a_max, selective)


def damped_inverse(jac: torch.Tensor, damping_sq: torch.Tensor | float) -> DLSInverse:
    """DLS inverse with a given damping ``a^2`` (scalar or ``(...)``), e.g. a constant damping."""
    return _filtered_inverse(jac, damping_sq)


def pseudo_inverse(jac: torch.Tensor) -> DLSInverse:
    """Undamped Moore-Penrose inverse ``J^+``: the reference that blows up near a singularity.

    Only exactly-zero singular values are dropped, so ``1 / sigma_min`` is applied however small
    ``sigma_min`` is (the behaviour the damping exists to prevent).
    """
    return _filtered_inverse(jac, 0.0)
