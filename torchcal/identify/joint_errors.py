"""All joint-space errors of a model in one place: the joints the geometric chain is evaluated at.

A fitted result, a model folder's metadata and the residual stage all need ``q + dq(q)`` with
every identified joint-space term (gravity compliance, first harmonics); this module is the one
implementation they share.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from torchcal.identify.compliance import GravityCompliance
from torchcal.identify.harmonics import JointHarmonics
from torchcal.kinematics.robot import RobotModel

METADATA_KEYS = {"compliance": "gravity_compliance", "harmonics": "joint_harmonics"}


@dataclass(frozen=True)
class JointSpaceErrors:
    """Identified joint-space terms; either may be ``None``."""

    compliance: GravityCompliance | None = None
    harmonics: JointHarmonics | None = None

    @property
    def empty(self) -> bool:
        return self.compliance is None and self.harmonics is None

    def effective_joints(self, robot: RobotModel, q: torch.Tensor) -> torch.Tensor:
        """The joint angles (rad) the arm actually takes at commanded ``q`` ``(B, N)`` rad."""
        dq = torch.zeros_like(q)
        if self.compliance is not None:
            dq = dq + self.compliance.deflection(robot, q)
        if self.harmonics is not None:
            dq = dq + self.harmonics.deflection(q)
        return q + dq

    @classmethod
    def of(cls, result) -> JointSpaceErrors:
        """The terms of a fit result (anything with ``compliance`` / ``harmonics`` attributes)."""
        return cls(getattr(result, "compliance", None), getattr(result, "harmonics", None))

    @classmethod
    def from_metadata(cls, metadata: dict) -> JointSpaceErrors:
        """The terms stored in a model folder's ``calibration.json``."""
        compliance = metadata.get(METADATA_KEYS["compliance"])
        harmonics = metadata.get(METADATA_KEYS["harmonics"])
        return cls(GravityCompliance.from_json(compliance) if compliance else None,
                   JointHarmonics.from_json(harmonics) if harmonics else None)

    def to_metadata(self) -> dict:
        """Entries for ``calibration.json`` (only the terms that are present)."""
        out = {}
        if self.compliance is not None:
            out[METADATA_KEYS["compliance"]] = self.compliance.to_json()
        if self.harmonics is not None:
            out[METADATA_KEYS["harmonics"]] = self.harmonics.to_json()
        return out

    def shifted(self, index: torch.Tensor, delta: torch.Tensor) -> JointSpaceErrors:
        """These terms with the coefficients ``index`` ``(K, 2)`` (row, joint) moved by ``delta`` ``(K,)``.

        Rows count as the joint fit stacks them (:func:`~torchcal.identify.joint_fit.fit_joint_errors`):
        the compliance's points first (rad/m), then the harmonics' rows (rad).
        """
        rows = [t.coefficients.clone() for t in (self.compliance, self.harmonics) if t is not None]
        stacked = torch.cat(rows) if rows else torch.zeros(0, 0, dtype=torch.float64)
        for (row, joint), d in zip(index.tolist(), delta.tolist(), strict=True):
            if row >= stacked.shape[0]:
                raise ValueError(f"coefficient row {row} beyond the terms' {stacked.shape[0]} rows")
            stacked[row, joint] += d
        n_points = 0 if self.compliance is None else self.compliance.coefficients.shape[0]
        return JointSpaceErrors(
            None if self.compliance is None else replace(self.compliance, coefficients=stacked[:n_points]),
            None if self.harmonics is None else replace(self.harmonics, coefficients=stacked[n_points:]))
