"""Periodic joint errors identified with the geometry: ``dq_j = sum_k a_kj sin(k q_j) + b_kj cos(k q_j)``.

Model. An eccentric gear, pulley or encoder disc makes the joint's true angle differ from the
reading by a once-per-revolution sinusoid (``first``); gear tooth and bearing errors, an
elliptic encoder disc or a strain-wave gear add the higher orders of any periodic shape
(``fourier2`` .. ``fourier4``: a Fourier series of order ``K`` per joint). Written in the
commanded angle ``q`` (rad) the error is linear in the coefficients (rad), so the TCP
displacement per coefficient is ``sin(k q_j)`` or ``cos(k q_j)`` times the ``theta_j`` column of
the position Jacobian: the series is learned by the same Gauss-Newton / LM solve as the geometry,
through the differentiable kinematics (:mod:`torchcal.identify.joint_fit`).

Smoothness. A series of order ``K > 1`` carries a Gaussian prior on its coefficients with 1-sigma
``s / k^p`` at order ``k`` (:data:`SMOOTHNESS_POWER` ``p``: a penalty growing as ``k^2p``, a
smooth curve unless the data insist); the scale ``s`` is chosen by the evidence (marginal
likelihood) of the joint fit, and ``K`` by the grouped cross-validation of the model-selection
stage. ``first`` keeps no prior, as it always had.

Why the last joint has none. A reflector a few mm off the last axis turns with that joint: its
position is ``R(q_N) r``, a first harmonic of ``q_N`` in the TCP. An error ``dq_N`` of order ``k``
moves the TCP by ``dq_N (z_N x R(q_N) r)``: orders ``k - 1`` and ``k + 1`` of ``q_N``, so order 2
aliases with the lever (order 1) and order 1 with the tool offset (order 0) and with it. Fitted
on the grid poses of real sets, a last-joint first harmonic took 0.62 rad (UR5) and 1.10 rad
(WAM): it stood for that lever, which the tool offset already models. With the reflector on the
axis ``dq_N`` has no effect at all. So the basis is zero there, at every order.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

#: Exponent ``p`` of the smoothness prior: order ``k`` has 1-sigma ``s / k^p``.
SMOOTHNESS_POWER = 1.0
#: Candidate prior scales ``s`` (rad) of a Fourier series; the evidence picks one.
SMOOTHNESS_SCALES_RAD = (2e-5, 1e-4, 5e-4, 2.5e-3)


def series_terms(order: int) -> tuple[str, ...]:
    """``("sin", "cos", "sin2", "cos2", ...)`` up to ``order``."""
    return tuple(name for k in range(1, order + 1) for name in ((f"sin{k}", f"cos{k}") if k > 1 else ("sin", "cos")))


HARMONIC_SETS: dict[str, tuple[str, ...]] = {"none": (), "first": ("sin", "cos"),
                                             **{f"fourier{k}": series_terms(k) for k in (2, 3, 4)}}


def term_order(name: str) -> int:
    """The order ``k`` of a term ``sin``, ``cos``, ``sin3``, ..."""
    kind, digits = name[:3], name[3:]
    if kind not in ("sin", "cos") or (digits and not digits.isdigit()) or digits in ("0", "1"):
        raise ValueError(f"unknown harmonic term '{name}'; choose sin, cos, sin<k> or cos<k> (k >= 2)")
    return int(digits) if digits else 1


def is_series(terms: tuple[str, ...]) -> bool:
    """Whether ``terms`` is a learned series of order > 1 (it carries the smoothness prior)."""
    return any(term_order(t) > 1 for t in terms)


def harmonic_basis(q: torch.Tensor, terms: tuple[str, ...]) -> torch.Tensor:
    """``(B, len(terms), N)``: ``sin(k q_j)`` / ``cos(k q_j)`` of commanded joints ``q`` ``(B, N)`` rad; zero on the last joint."""
    funcs = {"sin": torch.sin, "cos": torch.cos}
    out = []
    for name in terms:
        k = term_order(name)
        value = funcs[name[:3]](k * q).clone()
        value[:, -1] = 0.0  # see the module docstring: a last-joint term aliases with the reflector lever
        out.append(value)
    return torch.stack(out, 1) if out else q.new_zeros(q.shape[0], 0, q.shape[1])


@dataclass(frozen=True)
class JointHarmonics:
    """Identified periodic joint errors: ``coefficients (2K, N)`` rad, rows ``a_1, b_1, a_2, b_2, ...``.

    ``a_k`` multiplies ``sin(k q)``, ``b_k`` ``cos(k q)``; ``K = 1`` is the first harmonics.
    ``sigma`` (same shape, rad) is the 1-sigma from the joint fit's covariance; a coefficient the
    data could not separate from the geometry is 0 with sigma 0. ``prior_scale_rad`` is the
    smoothness prior's ``s`` the evidence chose (``None``: no prior).
    """

    coefficients: torch.Tensor
    sigma: torch.Tensor | None = None
    prior_scale_rad: float | None = None

    @property
    def order(self) -> int:
        return self.coefficients.shape[0] // 2

    @property
    def set_name(self) -> str:
        """The ``joint_harmonics`` option that fits this series (``first``, ``fourier2``, ...)."""
        return "first" if self.order == 1 else f"fourier{self.order}"

    @property
    def label(self) -> str:
        return "first joint harmonics" if self.order == 1 else f"joint Fourier series (order {self.order})"

    def _orders(self, q: torch.Tensor) -> torch.Tensor:
        return torch.arange(1, self.order + 1, dtype=q.dtype, device=q.device)

    def deflection(self, q: torch.Tensor) -> torch.Tensor:
        """Joint error ``(B, N)`` rad at commanded joints ``q`` ``(B, N)`` rad."""
        basis = harmonic_basis(q, series_terms(self.order))
        return (basis * self.coefficients.to(q)).sum(1)

    def slope(self, q: torch.Tensor) -> torch.Tensor:
        """``d dq_j / d q_j`` ``(B, N)`` at commanded joints ``q`` ``(B, N)`` rad (zero on the last joint)."""
        c = self.coefficients.to(q)
        angle = q.unsqueeze(1) * self._orders(q)[None, :, None]  # (B, K, N)
        k = self._orders(q)[None, :, None]
        out = (k * (c[0::2] * torch.cos(angle) - c[1::2] * torch.sin(angle))).sum(1)
        out[:, -1] = 0.0
        return out

    def amplitude(self) -> torch.Tensor:
        """``sqrt(sum_k a_k^2 + b_k^2)`` per joint, rad."""
        return self.coefficients.norm(dim=0)

    def to_json(self) -> dict:
        data: dict = {"coefficients_rad": self.coefficients.tolist(),
                      "model": "dq_j = sum_k a_kj sin(k q_j) + b_kj cos(k q_j), rows a_1, b_1, a_2, b_2, ...; "
                               "the last joint has none"}
        if self.sigma is not None:
            data["sigma_rad"] = self.sigma.tolist()
        if self.prior_scale_rad is not None:
            data["smoothness_prior"] = {"scale_rad": self.prior_scale_rad, "power": SMOOTHNESS_POWER,
                                        "sigma_of_order_k": "scale_rad / k**power", "chosen_by": "evidence"}
        return data

    @classmethod
    def from_json(cls, data: dict) -> JointHarmonics:
        sigma = data.get("sigma_rad")
        prior = data.get("smoothness_prior")
        return cls(torch.tensor(data["coefficients_rad"], dtype=torch.float64),
                   None if sigma is None else torch.tensor(sigma, dtype=torch.float64),
                   None if not prior else float(prior["scale_rad"]))
