"""Controller-side runner of an exported compensator: onnxruntime and numpy only.

This module (and what it imports: :mod:`torchcal.errors`) never imports torch, so a controller
PC needs neither torch nor the rest of torchcal's dependencies::

    from torchcal.compensate.runtime import CompensatorRuntime
    rt = CompensatorRuntime("exported_models/twin-default", threads=1)
    q_corrected = rt.correct(q_nominal_rad)        # (N,) or (B, N), rad
    tcp_error_m = rt.predict_error(q_rad)          # (3,) or (B, 3), m, robot base frame

Every ``.onnx`` file is checked against the SHA-256 of ``manifest.json`` before it is loaded,
and every call checks the joint count and refuses NaN or infinite joints.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Sequence

import numpy as np

from torchcal.errors import TorchcalError

MANIFEST_FORMAT = "torchcal-compensator/1"


class CompensatorError(TorchcalError, ValueError):
    """An exported compensator cannot be used as asked (tampered file, wrong robot, bad input)."""


class CompensatorRuntime:
    """Load the compensator and monitor graphs of an exported folder.

    Args:
        folder: the folder written by ``torchcal export`` (``manifest.json`` + ``.onnx`` files).
        precision: ``"float64"`` (default) or ``"float32"`` graphs.
        threads: onnxruntime intra-op threads; ``1`` for a real-time single core (default),
            ``None`` for onnxruntime's default (all cores, for batches).
        expected_robot: refuse the folder unless it was exported for this robot name.
        expected_joints: refuse the folder unless its joint names are these, in this order.
    """

    def __init__(
        self,
        folder: str | Path,
        *,
        precision: str = "float64",
        threads: int | None = 1,
        expected_robot: str | None = None,
        expected_joints: Sequence[str] | None = None,
    ) -> None:
        import onnxruntime as ort

        self.folder = Path(folder)
        path = self.folder / "manifest.json"
        if not path.is_file():
            raise CompensatorError(f"{self.folder}: no manifest.json (not an exported compensator folder)")
        try:
            self.manifest = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise CompensatorError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
        if self.manifest.get("format") != MANIFEST_FORMAT:
            raise CompensatorError(f"{path}: format {self.manifest.get('format')!r}, expected {MANIFEST_FORMAT!r}")
        if precision not in ("float64", "float32"):
            raise CompensatorError(f"precision must be 'float64' or 'float32', got {precision!r}")
        robot = self.manifest["robot"]
        if expected_robot is not None and robot != expected_robot:
            raise CompensatorError(f"{self.folder}: exported for robot '{robot}', not '{expected_robot}'")
        self.joint_names = tuple(self.manifest["joint_names"])
        if expected_joints is not None and tuple(expected_joints) != self.joint_names:
            raise CompensatorError(
                f"{self.folder}: joints {list(self.joint_names)} do not match the expected {list(expected_joints)}"
            )
        self.n_joints = int(self.manifest["n_joints"])
        self.dtype = np.float64 if precision == "float64" else np.float32
        suffix = "" if precision == "float64" else "_f32"
        options = ort.SessionOptions()
        options.log_severity_level = 3
        if threads is not None:
            options.intra_op_num_threads = int(threads)
            options.inter_op_num_threads = 1
            options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        self._compensator = self._load("compensator" + suffix, options, ort)
        self._monitor = self._load("monitor" + suffix, options, ort)

    def _load(self, key: str, options, ort):
        name = self.manifest["files"].get(key)
        if name is None:
            raise CompensatorError(f"{self.folder}: manifest lists no '{key}' graph")
        path = self.folder / name
        if not path.is_file():
            raise CompensatorError(f"{path}: listed in the manifest but missing")
        data = path.read_bytes()
        digest = hashlib.sha256(data).hexdigest()
        if digest != self.manifest["sha256"].get(key):
            raise CompensatorError(
                f"{path}: SHA-256 {digest[:12]}... does not match the manifest ({str(self.manifest['sha256'].get(key))[:12]}...); "
                "the file was changed after export"
            )
        session = ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])
        inputs = session.get_inputs()
        width = inputs[0].shape[-1] if inputs and len(inputs[0].shape) == 2 else None
        if len(inputs) != 1 or width != self.n_joints:
            raise CompensatorError(
                f"{path}: graph input {[(i.name, i.shape) for i in inputs]} does not match the manifest's {self.n_joints} joints"
            )
        return session, inputs[0].name

    def _prepare(self, q) -> tuple[np.ndarray, bool]:
        array = np.asarray(q, dtype=self.dtype)
        single = array.ndim == 1
        if single:
            array = array[None, :]
        if array.ndim != 2 or array.shape[1] != self.n_joints:
            raise CompensatorError(
                f"joint input has shape {tuple(np.shape(q))}; expected ({self.n_joints},) or (batch, {self.n_joints}) "
                f"for robot '{self.manifest['robot']}' ({', '.join(self.joint_names)}), rad"
            )
        if not np.isfinite(array).all():
            rows = np.flatnonzero(~np.isfinite(array).all(axis=1))
            raise CompensatorError(f"joint input has NaN or infinite values (rows {rows[:5].tolist()}); refusing to compensate")
        return np.ascontiguousarray(array), single

    def _run(self, graph, q) -> np.ndarray:
        session, name = graph
        array, single = self._prepare(q)
        out = session.run(None, {name: array})[0]
        return out[0] if single else out

    def correct(self, q_nominal) -> np.ndarray:
        """Corrected joint command(s), rad, for nominal command(s) ``(N,)`` or ``(B, N)`` in rad."""
        return self._run(self._compensator, q_nominal)

    def predict_error(self, q) -> np.ndarray:
        """Predicted TCP position error (real - nominal), m, robot ``base`` frame: ``(3,)`` or ``(B, 3)``."""
        return self._run(self._monitor, q)
