"""Position-first task-priority inverse kinematics along a path, in the path parameter (not in time).

One step from joints ``q`` (``Jp``, ``Jo``: position and orientation rows of the TCP's geometric
Jacobian, base frame; ``dp``, ``dw``: the path's change of position and orientation over the step
plus the pose-error feedback)::

    dq_p = Jp#  dp                              position task, damped inverse of Jp
    P    = I - Jp# Jp                           null-space projector of the position task
    Jo'  = Jo P
    dq_o = Jo'# (dw - Jo dq_p)                  orientation, only where the position leaves room
    dq   = dq_p + dq_o

(Siciliano and Slotine's task priority with Chiaverini's damping of the secondary task.) Both
inverses are filtered by their singular values, each damped by its own value::

    X# = V diag(s_i / (s_i^2 + a(s_i)^2)) U^T,   a(s)^2 = a_max^2 (1 - (s/eps)^2) for s < eps, else 0

so each inverse is exact outside its task's singular neighbourhood and continuous across it.

* At a wrist singularity ``Jp`` keeps rank 3 (the arm joints place the TCP) while ``Jo'`` loses a
  direction: the position stays exact and only the orientation component about the vanishing
  direction yields, by an amount that grows continuously as ``sigma(Jo')`` falls below ``eps``:
  no joint velocity jumps, and the wrist never spins to hold an orientation it can barely reach.
* At a shoulder or stretched-elbow singularity of the 6-D pose, a tool offset from the wrist centre
  keeps ``Jp`` regular (the wrist joints move the TCP), so again the orientation yields. ``Jp``
  itself loses a direction only where the TCP reaches the edge of its workspace: there the
  position yields too (the path is out of reach; the report says by how much).

Feedback: the position error is corrected in full at every step (``dp`` includes it; clipped to
the step's length, so a path beyond the reach, where the position must yield, leaves the arm
stretched towards it instead of swinging), the orientation error by the fraction ``gain * h``
(``gain`` in 1/m of path, ``h`` the step), so the orientation deviation left by the secondary
task's damping is recovered over about ``1/gain`` of path once the wrist leaves the neighbourhood.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchcal.core.errors import ModelError
from torchcal.kinematics import transforms as tf
from torchcal.kinematics.joint_jacobian import jacobian_columns
from torchcal.kinematics.mdh import chain_transforms


class TcpKinematics:
    """TCP pose ``T_base_tool`` and geometric Jacobian ``[v; w]`` (base frame) of commanded joints.

    Args:
        table: ``(N, 5)`` MDH rows (rad, m).
        T_base_0: ``(4, 4)`` base -> frame 0.
        T_n_tool: ``(4, 4)`` frame N -> tool (``T_n_flange @ T_flange_tool``).
        joint_map: commanded joints ``(B, N)`` -> the joints the chain turns by (joint-space
            errors of a calibrated model: gravity sag, harmonics), rad; ``None``: the identity.
    """

    def __init__(self, table: torch.Tensor, T_base_0: torch.Tensor, T_n_tool: torch.Tensor,
                 joint_map: Callable[[torch.Tensor], torch.Tensor] | None = None) -> None:
        self.table = table.to(torch.float64)
        self.base = T_base_0.to(self.table)
        self.tail = T_n_tool.to(self.table)
        self.joint_map = joint_map
        self.dof = int(self.table.shape[0])

    def _chain(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rot, pos = chain_transforms(q, self.table, all_frames=True)
        r_b, p_b = self.base[:3, :3], self.base[:3, 3]
        axes = torch.einsum("ij,...nj->...ni", r_b, rot[..., :, :, 2])
        origins = torch.einsum("ij,...nj->...ni", r_b, pos) + p_b
        pose = self.base @ tf.homogeneous(rot[..., -1, :, :], pos[..., -1, :]) @ self.tail
        return pose, jacobian_columns(axes, origins, pose[..., :3, 3])

    def pose(self, q: torch.Tensor) -> torch.Tensor:
        """``T_base_tool`` ``(..., 4, 4)`` at commanded joints ``q`` ``(..., N)`` rad."""
        return self(q)[0]

    def __call__(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pose ``(..., 4, 4)`` and Jacobian ``(..., 6, N)`` with respect to the commanded joints."""
        if self.joint_map is None:
            return self._chain(q)
        flat = q.reshape(-1, self.dof)
        pose, jac = self._chain(self.joint_map(flat))
        # d(q_chain)/d(q) by central differences (the joint-space terms are smooth, slow functions)
        h = 1e-6
        eye = torch.eye(self.dof, dtype=q.dtype, device=q.device) * h
        probes = torch.cat([flat[:, None, :] + eye, flat[:, None, :] - eye], 1).reshape(-1, self.dof)
        mapped = self.joint_map(probes).reshape(flat.shape[0], 2, self.dof, self.dof)
        dmap = ((mapped[:, 0] - mapped[:, 1]) / (2 * h)).transpose(-1, -2)  # (B, N_chain, N_cmd)
        jac = jac @ dmap
        return pose.reshape(*q.shape[:-1], 4, 4), jac.reshape(*q.shape[:-1], 6, self.dof)


@dataclass(frozen=True)
class PrioritySettings:
    """Damping and feedback of the position-first step (module docstring).

    Attributes:
        orientation_eps: singular value of ``Jo'`` below which the orientation yields, rad/rad.
        orientation_damping: damping ``a_max`` of the orientation task at ``sigma = 0``, rad/rad.
        position_eps: singular value of ``Jp`` below which the position yields, m/rad.
        position_damping: damping ``a_max`` of the position task at ``sigma = 0``, m/rad.
        gain: orientation-error feedback per metre of path, 1/m.
    """

    orientation_eps: float = 0.05
    orientation_damping: float = 0.05
    position_eps: float = 0.02
    position_damping: float = 0.01
    gain: float = 1000.0

    def __post_init__(self) -> None:
        for name in ("orientation_eps", "position_eps", "gain"):
            value = getattr(self, name)
            if not (value > 0.0 and value < float("inf")):
                raise ModelError(f"{name} must be a positive finite number, got {value}")
        for name in ("orientation_damping", "position_damping"):
            value = getattr(self, name)
            if not (value >= 0.0 and value < float("inf")):
                raise ModelError(f"{name} must be a finite number >= 0, got {value}")


def filtered_inverse(jac: torch.Tensor, eps: float, a_max: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Singular-value filtered inverse ``(..., N, M)`` of ``jac`` ``(..., M, N)`` and its singular values.

    Each singular value ``s`` is inverted as ``s / (s^2 + a(s)^2)`` with ``a(s)^2`` of the module
    docstring: ``1/s`` for ``s >= eps``, zero at ``s = 0``, continuous in between.
    """
    u, s, vh = torch.linalg.svd(jac, full_matrices=False)
    a2 = a_max**2 * (1.0 - (s / eps).clamp(max=1.0) ** 2)
    denom = s**2 + a2
    gain = torch.where(denom > 0, s / denom.clamp_min(torch.finfo(s.dtype).tiny), torch.zeros_like(s))
    return vh.transpose(-1, -2) @ (gain.unsqueeze(-1) * u.transpose(-1, -2)), s


@dataclass(frozen=True)
class PriorityStep:
    """One step: joint change ``dq`` ``(N,)`` rad and the tasks' smallest singular values."""

    dq: torch.Tensor
    sigma_position: torch.Tensor
    sigma_orientation: torch.Tensor


def priority_step(jac: torch.Tensor, dp: torch.Tensor, dw: torch.Tensor, settings: PrioritySettings) -> PriorityStep:
    """Position-first joint change for position change ``dp`` (m) and rotation ``dw`` (rad), base frame.

    ``jac`` ``(..., 6, N)``; ``dp``, ``dw`` ``(..., 3)``. Returns ``dq`` ``(..., N)``.
    """
    jp, jo = jac[..., :3, :], jac[..., 3:, :]
    jp_inv, sp = filtered_inverse(jp, settings.position_eps, settings.position_damping)
    dq_p = (jp_inv @ dp.unsqueeze(-1)).squeeze(-1)
    eye = torch.eye(jac.shape[-1], dtype=jac.dtype, device=jac.device)
    projector = eye - jp_inv @ jp
    jo_free = jo @ projector
    jo_inv, so = filtered_inverse(jo_free, settings.orientation_eps, settings.orientation_damping)
    rest = dw - (jo @ dq_p.unsqueeze(-1)).squeeze(-1)
    dq_o = (jo_inv @ rest.unsqueeze(-1)).squeeze(-1)
    return PriorityStep(dq=dq_p + dq_o, sigma_position=sp[..., -1], sigma_orientation=so[..., -1])


@dataclass(frozen=True)
class GeometricSolution:
    """Joints along the path parameter grid (pass 1, before any time law).

    Attributes:
        s: ``(G,)`` path parameter, m.
        q: ``(G, N)`` joints, rad.
        sigma_position / sigma_orientation: ``(G,)`` smallest singular value of ``Jp`` (m/rad)
            and of ``Jo'`` (rad/rad) at each grid point.
    """

    s: torch.Tensor
    q: torch.Tensor
    sigma_position: torch.Tensor
    sigma_orientation: torch.Tensor


def position_error(kin: TcpKinematics, q: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """``p_d - p(q)`` ``(..., 3)`` m, base frame."""
    return targets[..., :3, 3] - kin.pose(q)[..., :3, 3]


def follow_geometric(kin: TcpKinematics, poses_at: Callable[[torch.Tensor], torch.Tensor], s: torch.Tensor,
                     q0: torch.Tensor, settings: PrioritySettings) -> GeometricSolution:
    """Integrate the position-first step over the grid ``s`` ``(G,)`` (m) from joints ``q0`` ``(N,)``.

    ``poses_at(s)`` gives the desired poses ``(G, 4, 4)``. Each step takes the secant of the path
    between grid points as feed-forward (exact for the straight-line position) plus the feedback
    of the module docstring, through the mean of the step's inverses at its start and at the
    predicted end (Heun's rule: the orientation drift of a plain Euler step, second order in the
    step, would otherwise accumulate to 1e-4 deg over a few hundred mm).
    """
    targets = poses_at(s)
    q = q0.to(targets)
    out_q, out_sp, out_so = [], [], []
    for k in range(len(s)):
        pose, jac = kin(q)
        out_q.append(q)
        if k + 1 == len(s):
            step = priority_step(jac, torch.zeros(3).to(q), torch.zeros(3).to(q), settings)
            out_sp.append(step.sigma_position)
            out_so.append(step.sigma_orientation)
            break
        h = float(s[k + 1] - s[k])
        nxt = targets[k + 1]
        # feed-forward and the position error, the error clipped to the step's length: where the
        # position yields (beyond the reach) a growing error must not turn into growing steps
        error = targets[k, :3, 3] - pose[:3, 3]
        dp = nxt[:3, 3] - targets[k, :3, 3] + error * min(1.0, h / max(float(error.norm()), 1e-300))
        # feed-forward rotation of the path plus a fraction of the orientation error
        ff = tf.so3_log(nxt[:3, :3] @ targets[k, :3, :3].T)
        err = tf.so3_log(targets[k, :3, :3] @ pose[:3, :3].T)
        dw = ff + min(1.0, settings.gain * h) * err
        step = priority_step(jac, dp, dw, settings)
        out_sp.append(step.sigma_position)
        out_so.append(step.sigma_orientation)
        # Heun: the same increments through the Jacobian at the predicted joints, averaged
        _, jac_end = kin(q + step.dq)
        q = q + 0.5 * (step.dq + priority_step(jac_end, dp, dw, settings).dq)
    return GeometricSolution(s=s, q=torch.stack(out_q), sigma_position=torch.stack(out_sp),
                             sigma_orientation=torch.stack(out_so))


def correct_position(kin: TcpKinematics, q: torch.Tensor, targets: torch.Tensor, settings: PrioritySettings,
                     iterations: int = 2, max_correction: float = 1e-4) -> torch.Tensor:
    """Minimum-norm position corrections of joints ``q`` ``(..., N)`` onto ``targets`` ``(..., 4, 4)``.

    Damped like the position task, so a correction never jumps at a shoulder or elbow singularity;
    elsewhere two Newton steps put interpolated joints on the path point to round-off (an error
    above ``max_correction`` m, a path out of reach, is corrected by that much only). The
    orientation is left as the geometric pass made it (a position-and-orientation correction would
    undo the wrist's yielding near a singularity, and with it the planned joint accelerations).
    """
    for _ in range(iterations):
        pose, jac = kin(q)
        jp_inv, _ = filtered_inverse(jac[..., :3, :], settings.position_eps, settings.position_damping)
        error = targets[..., :3, 3] - pose[..., :3, 3]
        norm = error.norm(dim=-1, keepdim=True)
        error = error * (max_correction / norm.clamp_min(max_correction))  # where the path is out of reach
        q = q + (jp_inv @ error.unsqueeze(-1)).squeeze(-1)
    return q
