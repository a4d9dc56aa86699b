"""Forward kinematics and geometric Jacobian of MDH+beta chains as a fixed tensor graph.

The link transform of joint ``i`` is ``C_i Rz(q_i)`` with the constant
``C_i = Rx(alpha) Tx(a) Ry(beta) Rz(theta_i) Tz(d_i)`` (``Rz`` and ``Tz`` commute), and
``Rz(q) = cos(q) E_c + sin(q) E_s + E_0`` is linear in ``(cos q, sin q)``. So every link of a
batch is ``cos(q) K_c + sin(q) K_s + K_0`` with three constant ``(N, 4, 4)`` tensors: a handful of
ONNX nodes for all links at once, followed by ``N`` 4x4 products down the chain. The frames
are those of :mod:`torchcal.kinematics.mdh`, ``base`` to ``tool``, so the results equal
:meth:`ErrorModel.base_flange_pose` and :func:`torchcal.kinematics.joint_jacobian.geometric_jacobian`
(with an identity instrument frame) to rounding.

Several chains that share the joint vector (nominal and calibrated) are evaluated together on a
``chain`` axis, which halves the node count of graphs that need both.
"""

from __future__ import annotations

import torch
from torch import nn

from torchcal.kinematics import transforms as tf
from torchcal.kinematics.mdh import link_transform


def link_constants(table: torch.Tensor, T_base_0: torch.Tensor) -> torch.Tensor:
    """``K (3, N, 4, 4)``: ``[K_c, K_s, K_0]`` of the links of ``table`` ``(N, 5)`` (rad, m).

    ``T_base_0`` is folded into the first link, so the chain starts in the ``base`` frame.
    """
    alpha, a, beta, theta, d = table.to(torch.float64).unbind(-1)
    rot, pos = link_transform(alpha, a, beta, theta, d)
    c = tf.homogeneous(rot, pos)
    c = torch.cat([T_base_0.to(c) @ c[:1], c[1:]], 0)
    e_c = torch.diag(torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64))
    e_0 = torch.diag(torch.tensor([0.0, 0.0, 1.0, 1.0], dtype=torch.float64))
    e_s = torch.zeros(4, 4, dtype=torch.float64)
    e_s[0, 1], e_s[1, 0] = -1.0, 1.0
    return torch.stack([c @ e_c, c @ e_s, c @ e_0])


class ChainGraph(nn.Module):
    """``C`` serial chains with a common joint vector, as an exportable module.

    Args:
        tables: ``(C, N, 5)`` MDH+beta rows ``[alpha, a, beta, theta_offset, d]`` (rad, m).
        T_base_0: ``(4, 4)`` fixed ``base -> frame 0`` transform.
        T_end: ``(C, 4, 4)`` fixed ``frame N -> tool`` transform of each chain
            (``T_n_flange @ T_flange_tool``).
        dtype: float64 or float32 (constants are computed in float64, then cast).
        device: where the constants live.
    """

    # buffers, registered in __init__ (declared so that type checkers see tensors, not Tensor | Module)
    k_cos: torch.Tensor
    k_sin: torch.Tensor
    k_one: torch.Tensor
    t_end: torch.Tensor
    link_rot_t: torch.Tensor
    link_trans: torch.Tensor
    angle_map: torch.Tensor
    angle_shift: torch.Tensor
    link_map: torch.Tensor
    link_one: torch.Tensor

    def __init__(
        self,
        tables: torch.Tensor,
        T_base_0: torch.Tensor,
        T_end: torch.Tensor,
        *,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__()
        k = torch.stack([link_constants(t, T_base_0) for t in tables], 1)  # (3, C, N, 4, 4)
        self.register_buffer("k_cos", k[0].to(device, dtype))
        self.register_buffer("k_sin", k[1].to(device, dtype))
        self.register_buffer("k_one", k[2].to(device, dtype))
        self.register_buffer("t_end", T_end.to(torch.float64).unsqueeze(1).to(device, dtype))  # (C, 1, 4, 4)
        # the constant link transforms C_i themselves, for :meth:`positions`: rotation transposed
        # (row-vector points) and translation, (C, N, 3, 3) and (C, N, 1, 3)
        links = k[0] + k[2]  # C_i E_c + C_i E_0 = C_i
        self.register_buffer("link_rot_t", links[..., :3, :3].transpose(-1, -2).contiguous().to(device, dtype))
        self.register_buffer("link_trans", links[..., :3, 3].unsqueeze(-2).to(device, dtype))
        self.n_joints = n = int(tables.shape[-2])
        # :meth:`single` (first chain): angles [q_i + pi/2, q_i] by one product, one Sin gives
        # [cos q_i, sin q_i], and one more product assembles every link, (B, 2N) @ (2N, 16N)
        angle_map = torch.zeros(n, 2 * n, dtype=torch.float64)
        link_map = torch.zeros(2 * n, 16 * n, dtype=torch.float64)
        for i in range(n):
            angle_map[i, 2 * i] = angle_map[i, 2 * i + 1] = 1.0
            link_map[2 * i, 16 * i : 16 * i + 16] = k[0, 0, i].reshape(16)
            link_map[2 * i + 1, 16 * i : 16 * i + 16] = k[1, 0, i].reshape(16)
        shift = torch.zeros(2 * n, dtype=torch.float64)
        shift[0::2] = torch.pi / 2
        self.register_buffer("angle_map", angle_map.to(device, dtype))
        self.register_buffer("angle_shift", shift.to(device, dtype))
        self.register_buffer("link_map", link_map.to(device, dtype))
        self.register_buffer("link_one", k[2, 0].reshape(16 * n).to(device, dtype))

    def forward(self, q: torch.Tensor, with_frames: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """TCP poses ``T_base_tool`` ``(B, C, 4, 4)`` for joints ``q`` ``(B, N)`` rad.

        With ``with_frames``, also ``T_base_i`` ``(B, C, N, 4, 4)`` of every joint frame (joint
        ``i`` turns about the z axis of frame ``i``, through its origin); else ``None``.
        """
        angle = q.reshape(-1, 1, self.n_joints, 1, 1)  # one node (unsqueezes would be three)
        links = torch.cos(angle) * self.k_cos + torch.sin(angle) * self.k_sin + self.k_one
        parts = torch.split(links, 1, dim=2)  # N x (B, C, 1, 4, 4)
        pose = parts[0]
        frames = [pose]
        for link in parts[1:]:
            pose = pose @ link
            frames.append(pose)
        tcp = (pose @ self.t_end)[:, :, 0]
        if not with_frames:
            return tcp, None
        return tcp, torch.cat(frames, 2)

    def single(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """TCP pose ``(B, 1, 4, 4)`` and joint frames ``(B, N, 4, 4)`` of a one-chain graph (``C = 1``).

        :meth:`forward` in fewer nodes, for the compensator's iteration: in float64 one Sin gives
        cosines and sines (``cos q = sin(q + pi/2)``, within 1e-15 of ``cos``) and two products
        assemble all links; then ``N`` products down the chain and one to the tool. (float32
        keeps a Cos and a Sin: ``q + pi/2`` would round the angle by ~5e-7 rad there.)
        """
        if self.k_cos.shape[0] != 1:
            raise ValueError("single() is for a graph of one chain")
        n = self.n_joints
        if self.link_map.dtype == torch.float64:
            cos_sin = torch.sin(q @ self.angle_map + self.angle_shift)  # (B, 2N): cos q_i, sin q_i
            links = (cos_sin @ self.link_map + self.link_one).reshape(-1, n, 4, 4)
        else:
            angle = q.reshape(-1, n, 1, 1)
            links = torch.cos(angle) * self.k_cos[0] + torch.sin(angle) * self.k_sin[0] + self.k_one[0]
        parts = torch.split(links, 1, dim=1)  # N x (B, 1, 4, 4)
        pose = parts[0]
        frames = [pose]
        for link in parts[1:]:
            pose = pose @ link
            frames.append(pose)
        return pose @ self.t_end[0], torch.cat(frames, 1)

    def positions(self, q: torch.Tensor) -> torch.Tensor:
        """TCP positions ``(B, C, 3)`` in ``base``, m, for joints ``q`` ``(B, N)`` rad.

        The tool point is carried from the last link back to the base, ``p <- C_i Rz(q_i) p``:
        a 2-D rotation of ``(x, y)`` then a constant 3x4 affine map, on ``(C, B, 3)`` points. No
        ``(B, C, N, 4, 4)`` link tensor is ever formed, so large batches stay in cache
        (:meth:`forward` is memory-bound there).
        """
        angle = q.transpose(0, 1).unsqueeze(-1)  # (N, B, 1)
        cos = torch.split(torch.cos(angle), 1, dim=0)  # N x (1, B, 1)
        sin = torch.split(torch.sin(angle), 1, dim=0)
        point = self.t_end[:, :, :3, 3]  # (C, 1, 3) in frame N
        for i in reversed(range(self.n_joints)):
            x, y, z = torch.split(point, 1, dim=-1)
            c, s = cos[i], sin[i]
            if i == self.n_joints - 1:
                z = z + 0.0 * c  # the constant tool point gets its batch axis here
            turned = torch.cat([c * x - s * y, s * x + c * y, z], -1)
            point = turned @ self.link_rot_t[:, i] + self.link_trans[:, i]
        return point.transpose(0, 1)

# The Jacobian from the flattened frames (row-major 4x4 -> 16): z_i at 4r+2, o_i at 4r+3, and 1 at
# 15. With w = o_i - p (the TCP's origin subtracted at the slots 3, 7, 11), the position column
# z x (p - o) = w x z has the components w_(r+1) z_(r+2) - w_(r+2) z_(r+1): two gathers, one
# product, one constant matrix that takes the differences and passes z through.
_TCP_ORIGIN_MASK = [1.0 if k in (3, 7, 11) else 0.0 for k in range(16)]
_GATHER_A = [7, 11, 3, 11, 3, 7, 2, 6, 10]  # w1 w2 w0 | w2 w0 w1 | z0 z1 z2
_GATHER_B = [10, 2, 6, 6, 10, 2, 15, 15, 15]  # z2 z0 z1 | z1 z2 z0 | 1 1 1


def _jacobian_combination() -> torch.Tensor:
    a = torch.zeros(9, 6, dtype=torch.float64)
    for r in range(3):
        a[r, r], a[3 + r, r], a[6 + r, 3 + r] = 1.0, -1.0, 1.0
    return a


def geometric_jacobian_t(tcp: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
    """Transposed geometric Jacobian ``(B, N, 6)`` from :meth:`ChainGraph.single` outputs.

    Args:
        tcp: ``(B, 4, 4)`` TCP pose in ``base``.
        frames: ``(B, N, 4, 4)`` joint frames in ``base``.

    Returns:
        Row ``i`` = ``[z_i x (p - o_i), z_i]``: TCP linear velocity (m/rad) and tool angular
        velocity (rad/rad) in ``base`` per unit rate of joint ``i``. Eight ONNX nodes whatever
        the joint count (the cross products by gathers of the flattened frames).
    """
    n = frames.shape[-3]
    mask = torch.tensor(_TCP_ORIGIN_MASK, dtype=tcp.dtype, device=tcp.device)
    flat = frames.reshape(-1, n, 16) - tcp.reshape(-1, 1, 16) * mask
    first = flat.index_select(-1, torch.tensor(_GATHER_A, device=tcp.device))
    second = flat.index_select(-1, torch.tensor(_GATHER_B, device=tcp.device))
    return (first * second) @ _jacobian_combination().to(tcp)
