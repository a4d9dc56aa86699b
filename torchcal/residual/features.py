"""Input features of residual heads: what the geometric model leaves is periodic in the joints.

``phi(q) = [2 (q - mid) / span, sin q, cos q]`` per joint (``3 N`` features). (The module can
append a centred, scaled temperature; the fit never asks for it: the compensator and monitor a
controller runs take the joints alone, :func:`torchcal.model_selection.heads.make_features`.) Gear errors are harmonics of ``q`` (second harmonics given explicitly made the MLP stop earlier and fit worse on the twin);
gravity torques are sums of sines and cosines of joint sums, which a hidden layer builds from
these. The scaling constants are part of the head's stored state.
"""

from __future__ import annotations

import torch


class JointFeatures(torch.nn.Module):
    """``q (B, N) rad [, temperature (B,)]`` -> features ``(B, F)``; a plain module for ONNX."""

    # buffers, registered in __init__ (declared so that type checkers see tensors, not Tensor | Module)
    mid: torch.Tensor
    half_span: torch.Tensor
    t_mean: torch.Tensor
    t_scale: torch.Tensor

    def __init__(self, joint_limits: torch.Tensor, temperature: tuple[float, float] | None = None) -> None:
        super().__init__()
        lo, hi = joint_limits[:, 0], joint_limits[:, 1]
        self.register_buffer("mid", (lo + hi) / 2)
        self.register_buffer("half_span", ((hi - lo) / 2).clamp_min(1e-9))
        self.uses_temperature = temperature is not None
        t_mean, t_scale = temperature if temperature is not None else (0.0, 1.0)
        self.register_buffer("t_mean", torch.tensor(float(t_mean), dtype=torch.float64))
        self.register_buffer("t_scale", torch.tensor(float(t_scale), dtype=torch.float64))

    @property
    def size(self) -> int:
        return 3 * self.mid.shape[0] + (1 if self.uses_temperature else 0)

    def forward(self, q: torch.Tensor, temperature: torch.Tensor | None = None) -> torch.Tensor:
        parts = [(q - self.mid) / self.half_span, torch.sin(q), torch.cos(q)]
        if self.uses_temperature:
            if temperature is None:
                raise ValueError("this residual head was trained with temperature; pass it")
            parts.append(((temperature - self.t_mean) / self.t_scale).unsqueeze(-1))
        return torch.cat(parts, -1)
