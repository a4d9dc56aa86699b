"""Joint-space errors of a model as an exportable graph: ``dq(q)`` and its diagonal slope.

The calibrated chain of a model with joint-space errors (:mod:`torchcal.identify.joint_errors`)
turns by ``q + dq(q)`` at the commanded joints ``q`` (rad):

* gravity compliance (:mod:`torchcal.identify.compliance`): ``dq_j = sum_k c_kj tau_kj(q)``, with
  ``tau_kj`` the unit-weight gravity torque (m) of point ``k`` (``tcp`` or ``elbow``) about joint
  ``j`` on the *nominal* chain, ``base`` z up. For a lever ``l = p_k - o_j`` and joint axis ``z_j``,
  ``z_j . (l x (0, 0, -1)) = z_jy l_x - z_jx l_y``: four elementwise nodes on the joint frames the
  nominal chain graph already produces;
  a ``tcp3`` basis function (nonlinear compliance) is the ``tcp`` torque cubed;
* periodic joint errors (:mod:`torchcal.identify.harmonics`): ``dq_j = sum_k a_kj sin(k q_j) +
  b_kj cos(k q_j)`` (first harmonics: ``k = 1`` alone).

The slope ``d dq_j / d q_j`` of the series enters the compensator's Newton step (the Jacobian
with respect to the command is ``J(q + dq) diag(1 + slope)``): an amplitude of 0.05 rad slows the
contraction by that factor per step without it. The gravity term's own slope is ``c dtau/dq``,
~1e-4 rad/rad on the real sets, and is left out, as the residual head's Jacobian is.
"""

from __future__ import annotations

import torch
from torch import nn

from torchcal.identify.compliance import FRAME_POINTS, POINT_FUNCTIONS
from torchcal.identify.joint_errors import JointSpaceErrors


class JointErrorGraph(nn.Module):
    """``(q, nominal joint frames, nominal TCP) -> (dq, slope)`` for one model's joint-space errors.

    Args:
        errors: the identified terms (``JointSpaceErrors.from_metadata(stored.metadata)``).
        n_joints: the robot's joint count.
        dtype / device: of the graph's constants.
    """

    # buffers, registered in __init__ (declared so that type checkers see tensors, not Tensor | Module)
    gravity_coefficients: torch.Tensor
    cubic_mask: torch.Tensor
    harmonic_sin: torch.Tensor
    harmonic_cos: torch.Tensor
    harmonic_orders: torch.Tensor

    def __init__(self, errors: JointSpaceErrors, n_joints: int, *, dtype: torch.dtype = torch.float64,
                 device: str | torch.device = "cpu") -> None:
        super().__init__()
        compliance, harmonics = errors.compliance, errors.harmonics
        self.points: tuple[str, ...] = compliance.points if compliance is not None else ()
        self.has_harmonics = harmonics is not None
        if not (self.points or self.has_harmonics):
            raise ValueError("no joint-space errors to build a graph of")
        if compliance is not None and self.points:
            coefficients = compliance.coefficients.to(torch.float64).clone()  # (K, N) rad/m
            for k, name in enumerate(self.points):
                if name not in POINT_FUNCTIONS:
                    raise ValueError(f"unknown gravity point '{name}'")
                if name in FRAME_POINTS:  # an arm segment's weight loads only the joints before it
                    coefficients[k, FRAME_POINTS[name][1] :] = 0.0
            self.register_buffer("gravity_coefficients", coefficients.to(device, dtype))
            powers = [POINT_FUNCTIONS[name][1] for name in self.points]
            self.register_buffer("cubic_mask", torch.tensor([[float(p == 3)] for p in powers], dtype=dtype, device=device))
        if harmonics is not None:
            c = harmonics.coefficients.to(torch.float64).clone()  # rows a_1, b_1, a_2, b_2, ... rad
            c[:, -1] = 0.0  # as harmonic_basis: the last joint has none
            self.register_buffer("harmonic_sin", c[0::2].to(device, dtype))  # (K, N)
            self.register_buffer("harmonic_cos", c[1::2].to(device, dtype))
            orders = torch.arange(1, harmonics.order + 1, dtype=torch.float64)[:, None]
            self.register_buffer("harmonic_orders", orders.to(device, dtype))  # (K, 1)
        self.n_joints = n_joints

    @property
    def needs_frames(self) -> bool:
        """Whether :meth:`forward` reads the nominal chain (gravity terms do, harmonics do not)."""
        return bool(self.points)

    def forward(self, q: torch.Tensor, frames: torch.Tensor | None = None,
                tcp: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Joint errors ``(B, N)`` rad and the harmonics' slope ``(B, N)`` (``None`` without harmonics).

        Args:
            q: commanded joints ``(B, N)`` rad.
            frames: ``(B, N, 4, 4)`` joint frames of the *nominal* chain at ``q``, ``base`` frame
                (needed with gravity terms).
            tcp: ``(B, 3)`` nominal TCP position at ``q``, ``base``, m (needed with a ``tcp`` point).
        """
        dq: torch.Tensor | None = None
        if self.points:
            if frames is None:
                raise ValueError("gravity terms need the nominal joint frames")
            axes, origins = frames[..., :3, 2], frames[..., :3, 3]  # (B, N, 3)
            named: dict[str, torch.Tensor] = {}
            if any(POINT_FUNCTIONS[name][0] == "tcp" for name in self.points):
                if tcp is None:
                    raise ValueError("a 'tcp' gravity term needs the nominal TCP position")
                named["tcp"] = tcp
            for name in self.points:
                if name in FRAME_POINTS:
                    named[name] = origins[:, min(FRAME_POINTS[name][0], self.n_joints) - 1]
            points = torch.stack([named[POINT_FUNCTIONS[name][0]] for name in self.points], 1)  # (B, K, 3)
            lever = points.unsqueeze(2) - origins.unsqueeze(1)  # (B, K, N, 3)
            ax, ay = axes[..., 0].unsqueeze(1), axes[..., 1].unsqueeze(1)  # (B, 1, N)
            torque = ay * lever[..., 0] - ax * lever[..., 1]  # (B, K, N), m per unit weight
            # rows of a cubic basis function take tau^3 (m^3); a mask keeps the graph free of branches
            torque = torque + self.cubic_mask * (torque * torque * torque - torque)
            dq = (torque * self.gravity_coefficients).sum(1)
        slope = None
        if self.has_harmonics:
            angle = q.unsqueeze(1) * self.harmonic_orders  # (B, K, N): k q_j
            sin, cos = torch.sin(angle), torch.cos(angle)
            harmonic = (self.harmonic_sin * sin + self.harmonic_cos * cos).sum(1)
            dq = harmonic if dq is None else dq + harmonic
            slope = (self.harmonic_orders * (self.harmonic_sin * cos - self.harmonic_cos * sin)).sum(1)
        if dq is None:  # unreachable: __init__ refuses a graph with neither term
            raise RuntimeError("joint error graph without terms")
        return dq, slope
