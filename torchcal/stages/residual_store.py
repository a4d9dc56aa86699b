"""The learned residual stored in a model folder: ``residual.safetensors`` + ``residual.json``."""

from __future__ import annotations

from pathlib import Path

import torch

from torchcal.core.folder import write_member, write_member_json
from torchcal.residual import HEADS, ResidualHead
from torchcal.residual.features import JointFeatures
from torchcal.stages.files import read_json_member, read_tensors


class ResidualModule(torch.nn.Module):
    """``q (B, N) rad -> predicted TCP position error (B, 3)`` in ``base``, m (features + head)."""

    def __init__(self, features: JointFeatures, head: torch.nn.Module) -> None:
        super().__init__()
        self.features = features
        self.head = head

    def forward(self, q: torch.Tensor, temperature: torch.Tensor | None = None) -> torch.Tensor:
        return self.head(self.features(q, temperature)) * 1e-3


class StoredResidual:
    """A fitted head with its features; what ``StoredModel.residual`` holds."""

    def __init__(self, head: ResidualHead, features: JointFeatures, info: dict) -> None:
        self.head, self.features, self.info = head, features, info

    def to_torch_module(self) -> ResidualModule:
        return ResidualModule(self.features, self.head.module()).eval()

    def predict_base_error(self, q: torch.Tensor, temperature: torch.Tensor | None = None) -> torch.Tensor:
        """Predicted TCP position error ``(B, 3)`` in ``base``, m."""
        with torch.no_grad():
            module = self.to_torch_module().to(q.dtype)
            return module(q, temperature if self.features.uses_temperature else None)


def save_residual(folder: str | Path, residual: StoredResidual) -> None:
    from safetensors.torch import save

    folder = Path(folder)
    tensors = {f"head.{k}": v for k, v in residual.head.state().items()}
    tensors.update({f"features.{k}": v.detach().cpu().contiguous() for k, v in residual.features.state_dict().items()})
    write_member(folder, "residual.safetensors", save(tensors))
    write_member_json(folder, "residual.json", {
        "head": residual.head.name,
        "settings": residual.head.settings(),
        "uses_temperature": residual.features.uses_temperature,
        "output": "TCP position error in the base frame, m (head outputs mm)",
        **residual.info,
    })


def load_residual(folder: str | Path) -> StoredResidual:
    """The head of a model folder, checked: floating-point tensors of the shapes its settings give, no
    temperature input (the compensator and monitor take joints only), and one finite prediction.

    Raises:
        ValueError, KeyError, TypeError, RuntimeError: what does not hold (the store names the file).
    """
    folder = Path(folder)
    info = read_json_member(folder / "residual.json")
    tensors = read_tensors(folder / "residual.safetensors", {})
    for name, value in tensors.items():
        if not value.is_floating_point():
            raise ValueError(f"{name} is {value.dtype}, not floating point")
    if info.get("uses_temperature"):
        raise ValueError("the head takes temperature, which the compensator and the monitor cannot take (joints "
                         "only); refit the model")
    head_state = {k.removeprefix("head."): v for k, v in tensors.items() if k.startswith("head.")}
    feat_state = {k.removeprefix("features."): v for k, v in tensors.items() if k.startswith("features.")}
    n = feat_state["mid"].shape[0]
    limits = torch.stack([feat_state["mid"] - feat_state["half_span"], feat_state["mid"] + feat_state["half_span"]], 1)
    features = JointFeatures(limits)
    features.load_state_dict(feat_state)
    head_cls = HEADS[info["head"]]
    head = head_cls.from_state(info["settings"], head_state)
    if features.mid.shape != (n,) or features.half_span.shape != (n,):
        raise ValueError(f"the feature ranges hold {tuple(features.mid.shape)} and {tuple(features.half_span.shape)} "
                         f"entries for {n} joints")
    stored = StoredResidual(head, features, {k: v for k, v in info.items() if k not in ("head", "settings", "uses_temperature", "output")})
    probe = stored.predict_base_error(torch.zeros(1, n, dtype=torch.float64))  # shapes the settings do not give fail here
    if probe.shape != (1, 3) or not bool(torch.isfinite(probe).all()):
        raise ValueError(f"the head predicts {tuple(probe.shape)} values ({probe.flatten()[:3].tolist()}) for one pose, not a "
                         "finite 3-D error")
    return stored
