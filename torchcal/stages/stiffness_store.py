"""The stiffness stage of a model folder: ``stiffness.safetensors`` + ``stiffness.json``.

* ``stiffness.safetensors``: ``compliance`` ``(N, 6, 6)`` joint-frame compliance (SI: m/N,
  rad/(N m); zero rows and columns are rigid), ``stiffness`` ``(K,)`` and ``covariance_log``
  ``(K, K)`` of the fitted entries, ``T_instrument_base`` ``(4, 4)`` of the loading set-up.
* ``stiffness.json``: for people and scripts: each fitted entry with its value, unit, standard
  deviation and status; the entries the data could not observe (treated as rigid) and what they
  are confounded with; the frame of the wrench; the training data and fit metrics.

Entry names are ``k_j{i}_{tx|ty|tz|rx|ry|rz}``: the spring of joint ``i`` along / about the axes
of its MDH frame (see :mod:`torchcal.stiffness.vjm`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchcal.core.errors import ModelError
from torchcal.core.folder import write_member, write_member_json
from torchcal.stages.files import read_json_member, read_tensors

FORMAT = "torchcal-stiffness/1"
TENSORS = "stiffness.safetensors"
META = "stiffness.json"


@dataclass
class StoredStiffness:
    """A stiffness stage as loaded from a model folder.

    Attributes:
        names: fitted entries ``k_j{i}_{c}``.
        stiffness: ``(K,)`` N/m (translations) or N m/rad (rotations).
        covariance_log: ``(K, K)`` covariance of ``log k`` (NaN where at the rigid bound).
        compliance: ``(N, 6, 6)`` joint compliance, SI, what prediction and export use.
        T_instrument_base: ``(4, 4)`` the loading set-up's instrument frame (m).
        wrench_frame: frame of the wrenches of the data (``tool``: as an F/T sensor reports them).
        metadata: the content of ``stiffness.json``.
    """

    names: tuple[str, ...]
    stiffness: torch.Tensor
    covariance_log: torch.Tensor
    compliance: torch.Tensor
    T_instrument_base: torch.Tensor
    wrench_frame: str
    metadata: dict = field(default_factory=dict)

    @property
    def unobservable(self) -> tuple[str, ...]:
        return tuple(self.metadata.get("unobservable", ()))


def _finite_or_none(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def save_stiffness(folder: str | Path, estimate, metadata: dict) -> Path:
    """Write the stiffness stage of ``estimate`` (a :class:`~torchcal.stiffness.identify.StiffnessEstimate`).

    ``metadata`` (data provenance, metrics, geometry source) is merged into ``stiffness.json``.
    """
    from safetensors.torch import save

    folder = Path(folder)
    tensors = {
        "compliance": estimate.compliance.detach().cpu().contiguous(),
        "stiffness": estimate.stiffness.detach().cpu().contiguous(),
        "covariance_log": estimate.covariance_log.detach().cpu().contiguous(),
        "T_instrument_base": estimate.model.T_reference.detach().cpu().contiguous(),
    }
    write_member(folder, TENSORS, save(tensors))
    ident = estimate.identifiability
    at_bound, poor = set(estimate.at_bound), set(estimate.poorly_determined)
    parameters = {}
    for name, k, rel in zip(estimate.names, estimate.stiffness.tolist(), estimate.relative_std.tolist()):
        status = "at_rigid_bound" if name in at_bound else "poorly_determined" if name in poor else "identified"
        parameters[name] = {
            "value": k,
            "unit": "N m/rad" if name[-2] == "r" else "N/m",
            # first order: std(k) = k std(log k)
            "sigma": _finite_or_none(k * rel),
            "relative_std": _finite_or_none(rel),
            "status": status,
        }
    meta = {
        "format": FORMAT,
        "model": "virtual joint method: diagonal spring per MDH joint frame, first-order deflection J C J^T W",
        "units": {"rotational": "N m/rad", "translational": "N/m", "compliance": "SI (m/N, rad/(N m))"},
        "wrench_frame": estimate.wrench_frame,
        "wrench_convention": "[fx, fy, fz] N applied at the TCP, [tx, ty, tz] N m about the TCP",
        "parameters": parameters,
        "unobservable": list(ident.unobservable),
        "confounded": {k: list(v) for k, v in ident.confounded.items()},
        "treated_as_rigid": list(ident.unobservable) + list(estimate.at_bound),
        "poorly_determined": list(estimate.poorly_determined),
        "with_rotation": estimate.with_rotation,
        "sigma_ratio": estimate.sigma_ratio,
        "rms_residual_mm": estimate.rms_residual_m * 1e3,
        "solver": {"iterations": estimate.iterations, "converged": estimate.converged},
        **metadata,
    }
    write_member_json(folder, META, meta)
    return folder


def load_stiffness_stage(folder: str | Path, device: str | torch.device = "cpu") -> StoredStiffness | None:
    """The stiffness stage of a model folder, or ``None`` when it has none."""
    folder = Path(folder)
    if not (folder / META).is_file():
        return None
    meta = read_json_member(folder / META)
    if meta.get("format") != FORMAT:
        raise ModelError(f"{folder / META}: format {meta.get('format')!r}, expected {FORMAT!r}")
    if not (folder / TENSORS).is_file():
        raise ModelError(f"{folder}: {META} without {TENSORS}")
    t = read_tensors(folder / TENSORS, {"stiffness": 1, "covariance_log": 2, "compliance": 3, "T_instrument_base": 2},
                     finite=("stiffness", "compliance", "T_instrument_base"))
    return StoredStiffness(
        names=tuple(meta["parameters"]),
        stiffness=t["stiffness"].to(device),
        covariance_log=t["covariance_log"].to(device),
        compliance=t["compliance"].to(device),
        T_instrument_base=t["T_instrument_base"].to(device),
        wrench_frame=meta.get("wrench_frame", "tool"),
        metadata=meta,
    )
