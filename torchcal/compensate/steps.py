"""One Newton step of the compensator, in the two task orders it offers.

Both take the transposed geometric Jacobian ``J^T`` ``(B, N, 6)`` (columns: TCP linear velocity,
m/rad, then tool angular velocity, rad/rad, ``base`` frame) and the error ``e`` ``(B, 6, 1)``
(position m, then ``vee`` of the rotation error, rad), and return the joint step ``(B, N)`` rad.
They run in float64 whatever the graph's dtype (the caller casts; see
:mod:`torchcal.compensate.compensator`).

* :func:`pose_step`: damped least squares on the full 6-D pose, ``J^T (J J^T + lambda^2 I)^-1 e``
  with one 6x6 solve. Position and orientation share one damping, so near a wrist singularity
  (an orientation singularity) the position is corrected only partially too.
* :func:`position_first_step`: the position equations first, orientation as the secondary task
  in what the position leaves free (task-priority damped least squares, Siciliano and Slotine's
  ordering with Chiaverini's damping of the secondary task)::

      dq_p = Jp^T (Jp Jp^T + lp^2 I)^-1 e_p
      P    = I - Jp^T (Jp Jp^T + lp^2 I)^-1 Jp          (null-space projector of the position task)
      Jo'  = Jo P
      dq_o = Jo'^T (Jo' Jo'^T + lo^2 I)^-1 (e_o - Jo dq_p)

  Two 3x3 solves: onnxruntime's one-node ``Inverse`` by default, or the closed-form adjugate
  (:func:`~torchcal.compensate.linalg.inverse3`, standard operators only) for other runtimes. The orientation damping
  ``lo`` has a floor (``orientation_damping``): near the wrist singularity ``Jo'`` loses a
  direction, and without a floor holding the orientation would swing joints 4 and 6 by tenths
  of a radian for milliradians of orientation; with it the swing is bounded and the orientation
  deviation that remains is reported instead. ``dq_o`` lies in the position task's null space,
  so it leaves the position unchanged to first order; its second-order effect is removed by the
  position-only steps that end the iteration.

Each part of a step is bounded: scaled so that no joint moves more than ``max_step`` rad (position
part) or ``max_orientation_step`` rad (orientation part) in one step: a bounded move per
iteration whatever the pose; far from singularities the steps are milliradians and the bounds
never act.
"""

from __future__ import annotations

import torch

from torchcal.compensate.linalg import inverse3


def bounded(dq: torch.Tensor, max_step: torch.Tensor) -> torch.Tensor:
    """``dq`` ``(B, N)`` scaled down (direction kept) so that ``max |dq_j| <= max_step`` rad."""
    largest = dq.abs().amax(-1, keepdim=True)
    return dq * torch.clamp(max_step / largest, max=1.0)  # largest = 0 gives inf, clamped to 1


def pose_step(jac_t: torch.Tensor, error: torch.Tensor, damping_gain: torch.Tensor, damping_floor_sq: torch.Tensor,
              eye6: torch.Tensor, solve) -> torch.Tensor:
    """Damped least squares on the 6-D pose: ``J^T (J J^T + lambda^2 I)^-1 e`` ``(B, N)``.

    ``lambda^2 = damping_gain |e|^2 + damping_floor_sq``; ``solve(a, rhs, eye)`` solves the 6x6
    systems (:data:`torchcal.compensate.compensator.SOLVERS`).
    """
    lam2 = damping_gain * (error * error).sum(-2, keepdim=True) + damping_floor_sq  # (B, 1, 1)
    normal = jac_t.transpose(-1, -2) @ jac_t + lam2 * eye6
    return (jac_t @ solve(normal, error, eye6)).squeeze(-1)


def position_first_step(jac_t: torch.Tensor, error: torch.Tensor, damping_gain: torch.Tensor, damping_floor_sq: torch.Tensor,
                        orientation_damping_sq: torch.Tensor, eye3: torch.Tensor, max_step: torch.Tensor,
                        max_orientation_step: torch.Tensor, orientation: bool = True, inverse=inverse3) -> torch.Tensor:
    """Task-priority step ``(B, N)`` rad: position exactly, orientation in its null space (module docstring).

    Args:
        jac_t: ``(B, N, 6)`` transposed geometric Jacobian.
        error: ``(B, 6, 1)`` position (m) and rotation (rad) error.
        damping_gain, damping_floor_sq: position damping ``lp^2 = gain |e_p|^2 + floor^2``.
        orientation_damping_sq: floor of the orientation damping ``lo^2 = gain |e_o'|^2 + floor^2``.
        eye3: ``(3, 3)`` identity (a buffer, so it is a constant of the exported graph).
        max_step: largest joint move of the position part of the step, rad.
        max_orientation_step: largest joint move of the orientation part, rad (smaller: near the
            wrist singularity large wrist swings buy little orientation and, being nonlinear,
            can turn the tool the wrong way).
        orientation: ``False`` for a position-only step (structural: fixed at export).
        inverse: the 3x3 inverse (:func:`~torchcal.compensate.linalg.inverse3`, or
            :func:`~torchcal.compensate.linalg.ort_inverse`).
    """
    jp, jo = jac_t[..., :3], jac_t[..., 3:]
    ep, eo = error[:, :3], error[:, 3:]
    lam_p = damping_gain * (ep * ep).sum(-2, keepdim=True) + damping_floor_sq
    jp_t = jp.transpose(-1, -2)
    gram_inv = inverse(jp_t @ jp + lam_p * eye3)  # (B, 3, 3)
    dq_p = jp @ (gram_inv @ ep)  # (B, N, 1)
    step = bounded(dq_p.squeeze(-1), max_step)
    if not orientation:
        return step
    jo_free = jo - jp @ (gram_inv @ (jp_t @ jo))  # (Jo P)^T, (B, N, 3)
    eo_left = eo - jo.transpose(-1, -2) @ dq_p
    lam_o = damping_gain * (eo_left * eo_left).sum(-2, keepdim=True) + orientation_damping_sq
    dq_o = jo_free @ (inverse(jo_free.transpose(-1, -2) @ jo_free + lam_o * eye3) @ eo_left)
    return step + bounded(dq_o.squeeze(-1), max_orientation_step)
