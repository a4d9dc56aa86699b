"""One stiffness experiment in SI units: the data the stiffness identification consumes.

Files are read into it by the stiffness instrument (:mod:`torchcal.instruments.stiffness.data`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class StiffnessData:
    """One stiffness experiment, SI units, float64.

    Attributes:
        q: ``(B, N)`` joints, rad.
        wrench: ``(B, 6)`` ``[f (N); m (N m)]`` at the TCP, ``tool`` frame.
        deflection: ``(B, 3)`` loaded minus unloaded TCP position, ``instrument`` frame, m.
        rotation: ``(B, 3)`` rotation vector of ``R_loaded R_unloaded^T``, instrument frame, rad,
            or ``None``.
        unloaded: ``(B, 3)`` unloaded TCP position, ``instrument`` frame, m, or ``None`` (then
            the instrument frame is ``base``).
        path: source file, if any.
    """

    q: torch.Tensor
    wrench: torch.Tensor
    deflection: torch.Tensor
    rotation: torch.Tensor | None = None
    unloaded: torch.Tensor | None = None
    path: str | None = None

    def __len__(self) -> int:
        return int(self.q.shape[0])

    @property
    def n_joints(self) -> int:
        return int(self.q.shape[1])

    def subset(self, index: torch.Tensor | slice) -> StiffnessData:
        """Rows ``index`` of every table (same path)."""

        def pick(t: torch.Tensor | None) -> torch.Tensor | None:
            return None if t is None else t[index]

        return StiffnessData(
            q=self.q[index],
            wrench=self.wrench[index],
            deflection=self.deflection[index],
            rotation=pick(self.rotation),
            unloaded=pick(self.unloaded),
            path=self.path,
        )
