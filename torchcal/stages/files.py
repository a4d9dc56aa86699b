"""Reading the JSON and safetensors files of a model folder; malformed content is a ModelError naming the file."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from torchcal.core.errors import ModelError


def read_json_member(path: Path) -> dict:
    """A model folder's JSON object; anything else is a :class:`ModelError` naming the file."""
    try:
        doc = json.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ModelError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise ModelError(f"{path}: line {exc.lineno}, column {exc.colno}: invalid JSON ({exc.msg})") from None
    if not isinstance(doc, dict):
        raise ModelError(f"{path}: expected a JSON object, found {type(doc).__name__}")
    return doc


def read_tensors(path: Path, required: dict[str, int], finite: tuple[str, ...] | None = None) -> dict[str, torch.Tensor]:
    """The tensors of a safetensors file, each of ``required`` present with that many dimensions.

    ``required`` maps a tensor's name to its number of dimensions; the tensors named in
    ``finite`` (``None``: every floating-point tensor) must hold finite values only. Raises
    :class:`ModelError` naming the file and the tensor.
    """
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise ModelError(f"{path}: not a readable safetensors file ({exc})") from None
    for name, ndim in required.items():
        t = tensors.get(name)
        if t is None:
            raise ModelError(f"{path}: no tensor {name!r}")
        if t.dim() != ndim:
            raise ModelError(f"{path}: tensor {name!r} has {t.dim()} dimensions, expected {ndim}")
    for name in tensors if finite is None else finite:
        t = tensors.get(name)
        if t is not None and t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise ModelError(f"{path}: tensor {name!r} holds NaN or infinite values")
    return tensors
