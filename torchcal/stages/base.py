"""Typed model stages: what a model folder holds, in the order a prediction applies it.

A calibrated model is a chain of stages. Joint-space stages turn the commanded joints into the
joints the arm takes (gravity compliance, gear harmonics); the geometry puts those through the
calibrated kinematics; Cartesian stages add a TCP offset (a learned residual head, the deflection
under a load). :func:`torchcal.stages.geometry.predict_positions`, the exported graphs, the export
manifest and the report's model name loop over :meth:`torchcal.stages.store.StoredModel.stages`
instead of asking which optional part a folder has: each stage gives its graph piece
(:meth:`ModelStage.graph_part`), its manifest entry and its name in the report.

Frames and units: joints in rad; TCP offsets in the ``instrument`` frame of the calibration, m.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import torch

from torchcal.identify.compliance import POINT_SETS
from torchcal.identify.joint_errors import METADATA_KEYS
from torchcal.stiffness.vjm import deflection

if TYPE_CHECKING:
    from torchcal.identify.joint_errors import JointSpaceErrors
    from torchcal.kinematics.error_model import ErrorModel
    from torchcal.kinematics.robot import RobotModel
    from torchcal.stages.residual_store import StoredResidual
    from torchcal.stages.stiffness_store import StoredStiffness


@dataclass(frozen=True)
class StageTable:
    """A stage's table for a report: its title, column names and rows of text."""

    title: str
    columns: list[str]
    rows: list[list[str]]


def _number(value: Any, spec: str) -> str:
    """``value`` formatted with ``spec`` for a report table; ``n/a`` for anything not a number.

    Stored metadata writes a non-finite estimate (an unobservable entry, a degenerate fit) as JSON
    ``null``, which must not crash the report.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return "n/a"
    return format(value, spec)


class ModelStage(ABC):
    """One stage of a calibrated model.

    Attributes:
        name: the stage's key in manifests and reports (``geometry``, ``residual``...).
        space: ``joint`` (corrects joints before the chain), ``chain`` (the kinematics) or ``tcp``
            (adds an offset to the TCP after it).
        graph_inputs: inputs the exported graphs take for this stage beyond the joints (the
            stiffness stage: ``("wrench",)``).
    """

    name: ClassVar[str]
    space: ClassVar[str]
    graph_inputs: ClassVar[tuple[str, ...]] = ()

    def correct_joints(self, robot: RobotModel, q: torch.Tensor) -> torch.Tensor:
        """Joints ``(B, N)`` rad after this stage (joint-space stages; others return ``q``)."""
        return q

    def tcp_offset(
        self, q: torch.Tensor, *, temperature: torch.Tensor | None = None, wrench: torch.Tensor | None = None
    ) -> torch.Tensor | None:
        """TCP offset ``(B, 3)`` m, instrument frame, at commanded joints ``q`` (``tcp`` stages)."""
        return None

    @abstractmethod
    def describe(self) -> dict[str, bool]:
        """``stages`` entries of the manifest and the report (``{name: True}`` and sub-terms)."""

    def manifest_section(self) -> dict | None:
        """The stage's own entry of an export manifest (``manifest[name]``), or ``None``: what a
        controller engineer needs to know about this stage beyond its presence."""
        return None

    def report_table(self) -> StageTable | None:
        """The stage's own table in a model folder's report, or ``None`` (the chain's parameters
        and the joint-space terms have report sections of their own)."""
        return None

    def readme_section(self, manifest: dict) -> str | None:
        """The stage's section of an exported folder's README (markdown, from the export
        ``manifest``), or ``None``: what an integrator must do for this stage."""
        return None

    def graph_part(self) -> dict[str, Any]:
        """The stage's piece of the exported compensator and monitor graphs: keyword arguments of
        :class:`torchcal.compensate.compensator.CompensatorGraph` (or of the graph class its
        :attr:`graph_inputs` select). Nothing by default."""
        return {}

    @abstractmethod
    def title(self) -> str:
        """The stage in words, as the report names the model (``geometry + ... + mlp residual head``)."""


class JointErrorStage(ModelStage):
    """Joint-space errors identified with the geometry (gravity compliance, first harmonics)."""

    name: ClassVar[str] = "joint_errors"
    space: ClassVar[str] = "joint"

    def __init__(self, errors: JointSpaceErrors) -> None:
        self.errors = errors

    def correct_joints(self, robot: RobotModel, q: torch.Tensor) -> torch.Tensor:
        return self.errors.effective_joints(robot, q)

    def describe(self) -> dict[str, bool]:
        present = self.errors.to_metadata()
        return {key: key in present for key in METADATA_KEYS.values()}

    def graph_part(self) -> dict[str, Any]:
        return {"joint_errors": self.errors}

    def title(self) -> str:
        parts = []
        if self.errors.compliance is not None:
            points = tuple(self.errors.compliance.points)
            label = next((name for name, members in POINT_SETS.items() if members == points), "+".join(points))
            parts.append(f"gravity compliance ({label})")
        if self.errors.harmonics is not None:
            parts.append(self.errors.harmonics.label)
        return " + ".join(parts)


class GeometryStage(ModelStage):
    """The calibrated kinematic chain (MDH + beta, base and tool frames)."""

    name: ClassVar[str] = "geometry"
    space: ClassVar[str] = "chain"

    def __init__(self, model: ErrorModel, x: torch.Tensor) -> None:
        self.model, self.x = model, x

    def position(self, q_effective: torch.Tensor) -> torch.Tensor:
        """TCP ``(B, 3)`` m, instrument frame, at the joints the arm takes."""
        return self.model.tcp_position(q_effective, self.x)

    def describe(self) -> dict[str, bool]:
        return {"geometry": True}

    def graph_part(self) -> dict[str, Any]:
        return {"model": self.model, "x": self.x}

    def title(self) -> str:
        return "geometry"


class ResidualStage(ModelStage):
    """A learned residual head: the TCP error the kinematics leave, predicted from the joints."""

    name: ClassVar[str] = "residual"
    space: ClassVar[str] = "tcp"

    def __init__(self, residual: StoredResidual, R_instrument_base: torch.Tensor) -> None:
        self.residual, self.R_instrument_base = residual, R_instrument_base

    def tcp_offset(
        self, q: torch.Tensor, *, temperature: torch.Tensor | None = None, wrench: torch.Tensor | None = None
    ) -> torch.Tensor | None:
        error_base = self.residual.predict_base_error(q, temperature)
        return error_base @ self.R_instrument_base.T.to(error_base)

    def describe(self) -> dict[str, bool]:
        return {"residual": True}

    def graph_part(self) -> dict[str, Any]:
        return {"residual": self.residual.to_torch_module()}

    def title(self) -> str:
        return f"{self.residual.head.name} residual head"


class StiffnessStage(ModelStage):
    """Joint stiffness: the TCP deflection under a wrench at the tool (nothing without one)."""

    name: ClassVar[str] = "stiffness"
    space: ClassVar[str] = "tcp"
    graph_inputs: ClassVar[tuple[str, ...]] = ("wrench",)

    def __init__(self, stiffness: StoredStiffness, model: ErrorModel, x: torch.Tensor) -> None:
        self.stiffness, self.model, self.x = stiffness, model, x

    def tcp_offset(
        self, q: torch.Tensor, *, temperature: torch.Tensor | None = None, wrench: torch.Tensor | None = None
    ) -> torch.Tensor | None:
        if wrench is None:
            return None
        compliance = self.stiffness.compliance.to(q)
        return deflection(self.model, q, self.x, compliance, wrench.to(q), wrench_frame="tool")[..., :3]

    def describe(self) -> dict[str, bool]:
        return {"stiffness": True}

    def graph_part(self) -> dict[str, Any]:
        return {"compliance": self.stiffness.compliance.cpu()}

    def report_table(self) -> StageTable | None:
        parameters = self.stiffness.metadata.get("parameters") or {}
        rows = [[name, _number(p.get("value"), ".6g"), str(p.get("unit", "")), _number(p.get("sigma"), ".3g"),
                 str(p.get("status", ""))] for name, p in parameters.items()]
        return StageTable("Joint stiffness", ["parameter", "value", "unit", "1-sigma", "status"], rows)

    def readme_section(self, manifest: dict) -> str | None:
        wrench = manifest["wrench"]
        rigid = ", ".join(manifest[self.name]["treated_as_rigid"]) or "none"
        return f"""## Load (stiffness stage)

Both graphs take a second input `{wrench['name']}` (batch, 6): `fx, fy, fz` in N (force applied at
the TCP) and `tx, ty, tz` in N m (moment about the TCP), along {wrench['axes']}. Give the load the
robot will carry at that command; the compensated robot then puts its *loaded* TCP on the
nominal target. For a payload: {wrench['payload']}. A zero wrench compensates geometry only.
Stiffness entries treated as rigid (not observable from the stiffness data):
{rigid}.
"""

    def title(self) -> str:
        return "joint stiffness"

    def manifest_section(self) -> dict | None:
        meta = self.stiffness.metadata
        return {
            "model": "virtual joint method, first-order deflection J C J^T W at the current iterate",
            "entries": {n: p["value"] for n, p in meta.get("parameters", {}).items()},
            "units": meta.get("units"),
            "treated_as_rigid": meta.get("treated_as_rigid", []),
            "unobservable": meta.get("unobservable", []),
            "training_data": {k: meta.get("data", {}).get(k) for k in ("sha256", "n_poses")},
            "training_wrench": meta.get("training_wrench"),
            "fit_metrics": meta.get("fit_metrics"),
        }
