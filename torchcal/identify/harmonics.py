"""First-harmonic joint errors identified with the geometry: ``dq_j = a_j sin(q_j) + b_j cos(q_j)``.

Model. An eccentric gear, pulley or encoder disc makes the joint's true angle differ from the
reading by a once-per-revolution sinusoid; written as ``a sin q + b cos q`` (rad, ``q`` the
commanded angle in rad) it is linear in ``(a, b)``, so the TCP displacement per coefficient is
``sin q_j`` or ``cos q_j`` times the ``theta_j`` column of the position Jacobian.

Why the last joint has none. A reflector a few mm off the last axis turns with that joint: its
position is ``R(q_N) r``, a first harmonic of ``q_N`` in the TCP. Fitted on the grid poses of
real sets, a last-joint harmonic took 0.62 rad (UR5) and 1.10 rad (WAM): it stood for that lever,
which the tool offset already models, not for a joint error. So the basis is zero there.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

HARMONIC_SETS: dict[str, tuple[str, ...]] = {"none": (), "first": ("sin", "cos")}


def harmonic_basis(q: torch.Tensor, terms: tuple[str, ...]) -> torch.Tensor:
    """``(B, len(terms), N)``: ``sin q_j`` / ``cos q_j`` of commanded joints ``q`` ``(B, N)`` rad; zero on the last joint."""
    funcs = {"sin": torch.sin, "cos": torch.cos}
    out = []
    for name in terms:
        if name not in funcs:
            raise ValueError(f"unknown harmonic term '{name}'; choose sin or cos")
        value = funcs[name](q).clone()
        value[:, -1] = 0.0  # see the module docstring: a last-joint harmonic is a reflector lever
        out.append(value)
    return torch.stack(out, 1) if out else q.new_zeros(q.shape[0], 0, q.shape[1])


@dataclass(frozen=True)
class JointHarmonics:
    """Identified first harmonics: ``coefficients (2, N)`` rad, rows ``a`` (sin) and ``b`` (cos).

    ``sigma`` (same shape, rad) is the 1-sigma from the joint fit's covariance; a coefficient the
    data could not separate from the geometry is 0 with sigma 0.
    """

    coefficients: torch.Tensor
    sigma: torch.Tensor | None = None

    def deflection(self, q: torch.Tensor) -> torch.Tensor:
        """Joint error ``(B, N)`` rad at commanded joints ``q`` ``(B, N)`` rad."""
        basis = harmonic_basis(q, HARMONIC_SETS["first"])
        return (basis * self.coefficients.to(q)).sum(1)

    def amplitude(self) -> torch.Tensor:
        """``sqrt(a^2 + b^2)`` per joint, rad."""
        return self.coefficients.norm(dim=0)

    def to_json(self) -> dict:
        data = {"coefficients_rad": self.coefficients.tolist(),
                "model": "dq_j = a_j sin(q_j) + b_j cos(q_j), rows a, b; the last joint has none"}
        if self.sigma is not None:
            data["sigma_rad"] = self.sigma.tolist()
        return data

    @classmethod
    def from_json(cls, data: dict) -> JointHarmonics:
        sigma = data.get("sigma_rad")
        return cls(torch.tensor(data["coefficients_rad"], dtype=torch.float64),
                   None if sigma is None else torch.tensor(sigma, dtype=torch.float64))
