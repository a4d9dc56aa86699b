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
    return (jac_t @ solve(normal, error, eye6))[..., 0]  # indexing: squeeze of a dynamic shape exports as an If


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

    The products share work (about 40 ONNX nodes with the orientation, 20 without): one product
    ``Jp J^T`` gives ``Jp Jp^T`` and ``Jp Jo^T`` at once (the Gram matrix's lower rows are never
    formed: ``Jo Jp^T`` is the transpose of ``Jp Jo^T``), one product
    applies the position inverse to ``e_p`` and to ``Jp Jo^T`` together, and both parts are
    bounded by one set of nodes on the ``(B, N, 2)`` stack of the two moves.
    """
    jp = jac_t[..., :3]
    ep = error[:, :3]
    lam_p = damping_gain * (ep * ep).sum(-2, keepdim=True) + damping_floor_sq
    if not orientation:
        dq_p = jp @ (inverse(jp.transpose(-1, -2) @ jp + lam_p * eye3) @ ep)  # (B, N, 1)
        return bounded(dq_p[..., 0], max_step)
    top = jp.transpose(-1, -2) @ jac_t  # (B, 3, 6): [Jp Jp^T | Jp Jo^T], the Gram matrix's rows that are used
    gram_inv = inverse(top[..., :3] + lam_p * eye3)  # (B, 3, 3)
    solved = gram_inv @ torch.cat([ep, top[..., 3:]], -1)  # [G^-1 e_p | G^-1 Jp Jo^T], (B, 3, 4)
    moved = jp @ solved  # [dq_p | Jp^T G^-1 Jp Jo^T], (B, N, 4)
    dq_p = moved[..., :1]
    jo_free = jac_t[..., 3:] - moved[..., 1:]  # (Jo P)^T, (B, N, 3)
    eo_left = error[:, 3:] - top[..., 3:].transpose(-1, -2) @ solved[..., :1]  # e_o - Jo dq_p (Jo Jp^T = (Jp Jo^T)^T)
    lam_o = damping_gain * (eo_left * eo_left).sum(-2, keepdim=True) + orientation_damping_sq
    dq_o = jo_free @ (inverse(jo_free.transpose(-1, -2) @ jo_free + lam_o * eye3) @ eo_left)
    both = torch.cat([dq_p, dq_o], -1)  # (B, N, 2)
    limits = torch.stack([max_step, max_orientation_step])
    scale = torch.clamp(limits / both.abs().amax(-2, keepdim=True), max=1.0)  # as bounded(), per part
    return (both * scale).sum(-1)
