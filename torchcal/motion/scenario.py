"""The default motion scenario: a straight line through a wrist singularity of the twin robot.

The line is built *through* the singular pose rather than near it: take a joint vector with
``q5 = 0`` (axes 4 and 6 collinear, ``sigma_min = 0``), its TCP pose ``T_s``, and the line of
constant tool approach through ``T_s`` along ``direction``, while the tool spins about its own z
axis (approach) by ``spin`` rad from start to end. A spin about the approach axis leaves the
approach, and so the ``q5 = 0`` crossing, unchanged. The wrist centre moves along a parallel line
and the forearm axis sweeps across the approach direction, so ``q5`` changes sign at the line's
midpoint. Start joints come from continuation IK from the singular pose back to the start.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.error_model import ErrorModel
from torchcal.kinematics.ik import solve_ik
from torchcal.motion.path import LinePath

DEG = math.pi / 180.0
#: twin-kr6 joints (deg) of the default singular pose (``q5 = 0``).
DEFAULT_SINGULAR_Q_DEG = (10.0, -80.0, 10.0, 0.0, 0.0, 20.0)
#: default line direction in the instrument frame, its length (m) and tool spin (rad).
DEFAULT_DIRECTION = (1.0, 0.0, 0.0)
DEFAULT_LENGTH_M = 0.3
DEFAULT_SPIN_RAD = 0.5


@dataclass(frozen=True)
class SingularLine:
    """A line path through a singular pose and the joints that start it.

    Attributes:
        path: the :class:`LinePath`, instrument frame, m.
        q_start: ``(N,)`` joints at the start pose, rad (on the branch that reaches the singularity).
        q_singular: ``(N,)`` the singular joint vector at the line's midpoint, rad.
    """

    path: LinePath
    q_start: torch.Tensor
    q_singular: torch.Tensor


def singular_line(
    model: ErrorModel,
    x: torch.Tensor,
    q_singular: torch.Tensor | None = None,
    direction: torch.Tensor | None = None,
    length_m: float = DEFAULT_LENGTH_M,
    spin_rad: float = DEFAULT_SPIN_RAD,
    continuation_steps: int = 40,
) -> SingularLine:
    """Build the line of the module docstring for the model ``(model, x)``.

    Args:
        q_singular: ``(N,)`` joints with a singular Jacobian, rad (default: the twin's wrist pose).
        direction: ``(3,)`` line direction in the instrument frame (normalised here).
        length_m: line length, m; the singular pose is its midpoint.
        spin_rad: tool rotation about its approach axis over the line, rad.
    """
    dtype, device = torch.float64, x.device
    if q_singular is None:
        q_singular = torch.tensor(DEFAULT_SINGULAR_Q_DEG, dtype=dtype, device=device) * DEG
    u = torch.tensor(DEFAULT_DIRECTION, dtype=dtype, device=device) if direction is None else direction.to(dtype)
    if float(u.norm()) == 0.0:
        raise ModelError("singular line direction must be non-zero")
    u = u / u.norm()
    mid = model.tcp_pose(q_singular, x)
    spin = lambda angle: tf.rot_z(torch.tensor(angle, dtype=dtype, device=device))  # noqa: E731
    start, end = mid.clone(), mid.clone()
    start[:3, 3] -= 0.5 * length_m * u
    end[:3, 3] += 0.5 * length_m * u
    start[:3, :3] = mid[:3, :3] @ spin(-0.5 * spin_rad)
    end[:3, :3] = mid[:3, :3] @ spin(0.5 * spin_rad)
    path = LinePath(start, end)
    # Continuation from the singular midpoint: a damped solve picks the branch that passes the
    # singularity smoothly (q4 along the crossing direction), small steps keep to that branch.
    q = q_singular.clone()
    lams = torch.linspace(0.5, 0.0, continuation_steps + 1, dtype=dtype, device=device)[1:]
    for lam in lams:
        result = solve_ik(model, x, path.poses(lam), q, damping=1e-2, max_iterations=500)
        q = result.q
    if not bool(result.converged):
        raise ModelError(
            f"cannot reach the start of the singular line (position error {float(result.position_error) * 1e3:.3g} mm); "
            "choose a shorter line or another direction"
        )
    return SingularLine(path=path, q_start=q, q_singular=q_singular)


def perturbed_parameters(
    model: ErrorModel,
    seed: int = 0,
    length_error_mm: float = 0.3,
    angle_error_deg: float = 0.03,
    tool_error_mm: float = 0.5,
) -> torch.Tensor:
    """A "true" parameter vector: nominal plus Gaussian kinematic errors (the twin's magnitudes).

    Every MDH length/angle gets a 1-sigma ``length_error_mm`` / ``angle_error_deg`` error (``beta``
    only on Hayati rows), the tool offset ``tool_error_mm`` per axis. The base correction stays
    zero: the instrument frame is the robot ``base``, as a motion program sees it.
    """
    layout = model.layout
    gen = torch.Generator().manual_seed(seed)
    x = model.nominal_vector().cpu()
    sigma = torch.where(layout.is_angle(), math.radians(angle_error_deg), length_error_mm * 1e-3)
    mask = torch.zeros(layout.size, dtype=torch.bool)
    mask[layout.table_slice] = True
    for i in range(1, model.robot.dof + 1):
        if i not in model.parallel_joints:
            mask[layout.index(f"beta{i}")] = False
    x = x + torch.randn(layout.size, generator=gen, dtype=torch.float64) * sigma * mask
    x[layout.tool_slice.start : layout.tool_slice.start + 3] += (
        torch.randn(3, generator=gen, dtype=torch.float64) * tool_error_mm * 1e-3
    )
    return x.to(model.device)
