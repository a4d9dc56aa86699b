"""Controller-side runner of an exported compensator: onnxruntime and numpy only.

This module (and what it imports: :mod:`torchcal.core.errors`) never imports torch, so a controller
PC needs neither torch nor the rest of torchcal's dependencies::

    from torchcal.compensate.runtime import CompensatorRuntime
    rt = CompensatorRuntime("exported_models/twin-default", threads=1)
    q_corrected = rt.correct(q_nominal_rad)        # (N,) or (B, N), rad
    q_corrected, residual = rt.correct_with_residual(q_nominal_rad)
                                                   # residual: (2,) or (B, 2): position m, orientation rad
    q_corrected, residual = rt.correct_one(q_nominal_rad)
                                                   # one pose per control cycle: preallocated, bound buffers
    tcp_error_m = rt.predict_error(q_rad)          # (3,) or (B, 3), m, robot base frame

A folder exported with a stiffness stage (``manifest["stages"]["stiffness"]``) needs the
expected load too: ``rt.correct(q, wrench)`` with ``wrench`` ``(6,)`` or ``(B, 6)``, ``[fx, fy,
fz]`` N at the TCP and ``[tx, ty, tz]`` N m about it, in the frame ``manifest["wrench"]["frame"]``.

``manifest.json`` is checked against the folder's ``checksums.json`` and every ``.onnx`` file
against the SHA-256 the manifest records before it is loaded; each graph's inputs and outputs
must be those the manifest names. Every call checks the joint count and refuses non-numeric,
NaN or infinite joints (and wrenches) and joints outside ``joint_limits_rad`` (by more than
:data:`JOINT_LIMIT_TOLERANCE_RAD`). Every failure is a :class:`CompensatorError`.

One runner may be called from several threads: :meth:`CompensatorRuntime.correct_one`'s bound
buffers are used under a lock (onnxruntime's ``run`` is itself thread-safe).
"""

from __future__ import annotations

import hashlib
import json
import math
import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from torchcal.core.errors import TorchcalError

MANIFEST_FORMAT = "torchcal-compensator/1"
CHECKSUMS_FORMAT = "torchcal-checksums/1"

#: How far (rad) a joint may lie outside the manifest's limits and still be compensated: rounding of
#: a command at its limit (float32 keeps ~2.4e-7 rad at 3 rad).
JOINT_LIMIT_TOLERANCE_RAD = 1e-6

#: The element type onnxruntime reports for each dtype the manifest names.
_ORT_TYPES = {"float64": "tensor(double)", "float32": "tensor(float)"}


class CompensatorError(TorchcalError, ValueError):
    """An exported compensator cannot be used as asked (tampered file, wrong robot, bad input)."""


class CompensatorRuntime:
    """Load the compensator and monitor graphs of an exported folder.

    Args:
        folder: the folder written by ``torchcal export`` (``manifest.json`` + ``.onnx`` files).
        precision: ``"float64"`` (default) or ``"float32"`` graphs.
        threads: onnxruntime intra-op threads; ``1`` for a real-time single core (default),
            ``None`` for onnxruntime's default (all cores, for batches). With one thread no
            thread pool exists, so nothing spins between calls (``scripts/bench_onnx.py``
            measures the session options against one another).
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
        if precision not in ("float64", "float32"):
            raise CompensatorError(f"precision must be 'float64' or 'float32', got {precision!r}")
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
            raise CompensatorError(f"threads must be a whole number >= 1 (or None for onnxruntime's default), got {threads!r}")
        self.manifest = _read_manifest(self.folder)
        robot = self.manifest["robot"]
        if expected_robot is not None and robot != expected_robot:
            raise CompensatorError(f"{self.folder}: exported for robot '{robot}', not '{expected_robot}'")
        self.joint_names = tuple(self.manifest["joint_names"])
        if expected_joints is not None and tuple(expected_joints) != self.joint_names:
            raise CompensatorError(
                f"{self.folder}: joints {list(self.joint_names)} do not match the expected {list(expected_joints)}"
            )
        self.n_joints = self.manifest["n_joints"]
        self._limits = _joint_limits(self.manifest, self.folder / "manifest.json")
        # the per-call test in one pass: within the widened limits (NaN fails it), and finite where a joint has none
        self._low_ok = self._limits[0] - JOINT_LIMIT_TOLERANCE_RAD
        self._high_ok = self._limits[1] + JOINT_LIMIT_TOLERANCE_RAD
        self._unbounded = bool(np.isinf(self._limits).any())
        self._bounds = list(zip(self._low_ok.tolist(), self._high_ok.tolist(), strict=True))
        self.wrench_input = "wrench" in self.manifest and bool(self.manifest.get("stages", {}).get("stiffness"))
        self.precision = precision
        self.dtype = np.float64 if precision == "float64" else np.float32
        suffix = "" if precision == "float64" else "_f32"
        options = ort.SessionOptions()
        options.log_severity_level = 3
        if threads is not None:
            options.intra_op_num_threads = threads
            options.inter_op_num_threads = 1
            options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        self._compensator = self._load("compensator" + suffix, "compensator", options, ort)
        self._monitor = self._load("monitor" + suffix, "monitor", options, ort)
        self._bound: tuple | None = None  # correct_one's buffers, made on its first call
        self._bound_lock = threading.Lock()  # one caller at a time on those buffers

    def _bind_one(self):
        """Input and output buffers of one pose, bound to the compensator session once (IOBinding):
        a call then copies the joints in and runs, with no per-call dicts or output allocation."""
        session, names = self._compensator
        q = np.zeros((1, self.n_joints), dtype=self.dtype)
        outputs = [np.zeros((1, self.n_joints), dtype=self.dtype), np.zeros((1, 2), dtype=self.dtype)]
        binding = session.io_binding()
        binding.bind_cpu_input(names[0], q)
        for meta, array in zip(session.get_outputs(), outputs):
            binding.bind_output(meta.name, "cpu", 0, array.dtype, list(array.shape), array.ctypes.data)
        self._bound = (binding, q, outputs)
        return self._bound

    def correct_one(self, q_nominal) -> tuple[np.ndarray, np.ndarray]:
        """One corrected command ``(N,)`` rad and its residual ``(2,)`` (m, rad) for one nominal
        command ``(N,)`` rad: the controller's per-cycle call.

        The same checks as :meth:`correct` (joint count, finite input and output) on buffers bound
        to the session once; the returned arrays are fresh copies. A folder with a stiffness stage
        takes its wrench through :meth:`correct_with_residual`.
        """
        if self.wrench_input:
            raise CompensatorError(f"{self.folder}: this compensator has a stiffness stage; use correct_with_residual(q, wrench)")
        array = _numeric(q_nominal, "joint input")
        if array.shape != (self.n_joints,):
            raise CompensatorError(f"joint input has shape {array.shape}; expected ({self.n_joints},) for robot "
                                   f"'{self.manifest['robot']}' ({', '.join(self.joint_names)}), rad")
        self._check_joints(array[None, :])
        with self._bound_lock:
            binding, q, outputs = self._bound or self._bind_one()
            q[0] = array
            self._compensator[0].run_with_iobinding(binding)
            if not (np.isfinite(outputs[0]).all() and np.isfinite(outputs[1]).all()):
                raise CompensatorError(f"{self.folder}: no finite output for this pose ({self.precision} graph); keep the nominal command")
            return outputs[0][0].copy(), outputs[1][0].copy()

    def _check_joints(self, array: np.ndarray) -> None:
        """Refuse NaN or infinite joints, and joints outside the manifest's limits (``array`` ``(B, N)``, rad)."""
        if len(array) == 1:  # the per-cycle path: a few float comparisons (numpy's calls cost more on 6 values)
            if all(low <= v <= high and math.isfinite(v) for v, (low, high) in zip(array[0].tolist(), self._bounds)):
                return
        elif ((array >= self._low_ok) & (array <= self._high_ok)).all() and (not self._unbounded or np.isfinite(array).all()):
            return  # one comparison pass (NaN fails it); the messages below only for a refusal
        if not np.isfinite(array).all():
            rows = np.flatnonzero(~np.isfinite(array).all(axis=1))
            raise CompensatorError(f"joint input has NaN or infinite values (rows {rows[:5].tolist()}); refusing to compensate")
        low, high = self._limits
        outside = (array < self._low_ok) | (array > self._high_ok)
        if outside.any():
            row, joint = (int(v) for v in np.argwhere(outside)[0])
            raise CompensatorError(
                f"joint input row {row}: {self.joint_names[joint]} = {array[row, joint]:.6g} rad is outside its limits "
                f"[{low[joint]:.6g}, {high[joint]:.6g}] rad ({int(outside.any(axis=1).sum())} row(s) outside; joints "
                f"in degrees or another robot?); refusing to compensate")

    def _load(self, key: str, kind: str, options, ort):
        """The session of the manifest's graph ``key`` (``kind``: ``compensator`` or ``monitor``, whose
        output names the manifest lists) and its input names, checked against the manifest."""
        name = self.manifest["files"].get(key)
        if name is None:
            raise CompensatorError(f"{self.folder}: manifest lists no '{key}' graph")
        if not isinstance(name, str) or Path(name).name != name or name in ("", ".", ".."):
            raise CompensatorError(f"{self.folder / 'manifest.json'}: files.{key} must name a file inside the folder, got {name!r}")
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
        try:
            session = ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # noqa: BLE001 (onnxruntime's own exception types derive from Exception alone)
            raise CompensatorError(f"{path}: onnxruntime cannot load it ({str(exc).splitlines()[0]})") from None
        inputs = session.get_inputs()
        expected = [self.n_joints, 6] if self.wrench_input else [self.n_joints]
        widths = [i.shape[-1] if len(i.shape) == 2 else None for i in inputs]
        if widths != expected:
            raise CompensatorError(
                f"{path}: graph inputs {[(i.name, i.shape) for i in inputs]} do not match the manifest "
                f"({self.n_joints} joints{' and a 6-D wrench' if self.wrench_input else ''})"
            )
        element = _ORT_TYPES.get(str((self.manifest.get("dtypes") or {}).get(key, self.precision)))
        if any(i.type != element for i in inputs) or any(o.type != element for o in session.get_outputs()):
            raise CompensatorError(f"{path}: graph inputs and outputs are {[i.type for i in inputs]} -> "
                                   f"{[o.type for o in session.get_outputs()]}, not the manifest's {element} for '{key}'")
        outputs = (self.manifest.get("outputs") or {}).get(kind)
        if outputs is not None and [o.name for o in session.get_outputs()] != list(outputs):
            raise CompensatorError(f"{path}: graph outputs {[o.name for o in session.get_outputs()]} are not the "
                                   f"manifest's {kind} outputs {outputs}")
        return session, [i.name for i in inputs]

    def _prepare(self, q) -> tuple[np.ndarray, bool]:
        array = _numeric(q, "joint input")
        single = array.ndim == 1
        if single:
            array = array[None, :]
        if array.ndim != 2 or array.shape[1] != self.n_joints:
            raise CompensatorError(
                f"joint input has shape {tuple(np.shape(q))}; expected ({self.n_joints},) or (batch, {self.n_joints}) "
                f"for robot '{self.manifest['robot']}' ({', '.join(self.joint_names)}), rad"
            )
        self._check_joints(array)
        return np.ascontiguousarray(array, dtype=self.dtype), single

    def _prepare_wrench(self, wrench, batch: int) -> np.ndarray:
        if wrench is None:
            frame = self.manifest["wrench"].get("frame")
            raise CompensatorError(
                f"{self.folder}: this compensator has a stiffness stage; pass the expected wrench "
                f"(6,) or (batch, 6): fx, fy, fz in N, tx, ty, tz in N m, {frame} frame (zeros for no load)"
            )
        array = _numeric(wrench, "wrench")
        if array.ndim == 1:
            array = array[None, :]
        if array.ndim != 2 or array.shape[1] != 6 or array.shape[0] not in (1, batch):
            raise CompensatorError(f"wrench has shape {tuple(np.shape(wrench))}; expected (6,), (1, 6) or ({batch}, 6), N and N m")
        if not np.isfinite(array).all():
            raise CompensatorError("wrench has NaN or infinite values; refusing to compensate")
        return np.ascontiguousarray(np.broadcast_to(array, (batch, 6)), dtype=self.dtype)

    def _run(self, graph, q, wrench=None, outputs: int = 1):
        session, names = graph
        array, single = self._prepare(q)
        feeds = {names[0]: array}
        if self.wrench_input:
            feeds[names[1]] = self._prepare_wrench(wrench, array.shape[0])
        elif wrench is not None:
            raise CompensatorError(f"{self.folder}: this compensator has no stiffness stage; it takes no wrench")
        results = session.run(None, feeds)
        out = results[0] if outputs == 1 else np.concatenate([r.reshape(r.shape[0], -1) for r in results[:outputs]], 1)
        if not np.isfinite(out).all():
            # Never hand a controller NaN: float32 loses the solve at exactly singular poses.
            rows = np.flatnonzero(~np.isfinite(out).reshape(out.shape[0], -1).all(axis=1))
            raise CompensatorError(
                f"{self.folder}: no finite output for row(s) {rows[:10].tolist()} (pose at a singularity, "
                f"{self.precision} graph); use precision='float64' or keep the nominal command there"
            )
        if outputs == 1:
            return out[0] if single else out
        return tuple(r[0] if single else r for r in results[:outputs])

    def correct(self, q_nominal, wrench=None) -> np.ndarray:
        """Corrected joint command(s), rad, for nominal command(s) ``(N,)`` or ``(B, N)`` in rad.

        ``wrench``: the expected load ``(6,)`` or ``(B, 6)`` (N, N m, see the manifest's
        ``wrench``), required by a compensator with a stiffness stage, refused by one without.
        """
        return self._run(self._compensator, q_nominal, wrench)

    def correct_with_residual(self, q_nominal, wrench=None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`correct` and the compensator's ``residual``: ``(2,)`` or ``(B, 2)`` per command,
        the model's remaining TCP position error (m) and the tool's orientation deviation from
        the nominal target (rad) at the corrected command.

        A position error above the controller's tolerance marks a command the compensator could
        not solve (a pose at or near a position singularity); the orientation deviation is what the
        position-first task gave up near a wrist singularity (``manifest["solver"]``).
        """
        if len(self._compensator[0].get_outputs()) < 2:
            raise CompensatorError(f"{self.folder}: this compensator was exported without a residual output; export it again")
        return self._run(self._compensator, q_nominal, wrench, outputs=2)

    def predict_error(self, q, wrench=None) -> np.ndarray:
        """Predicted TCP position error (real - nominal), m, robot ``base`` frame: ``(3,)`` or ``(B, 3)``.

        ``wrench`` as for :meth:`correct` (the real TCP is then the loaded one).
        """
        return self._run(self._monitor, q, wrench)


def _numeric(values, what: str) -> np.ndarray:
    """``values`` as a float64 array; anything but real numbers (text, booleans, complex) is refused."""
    try:
        array = np.asarray(values)
    except (ValueError, TypeError) as exc:  # ragged nested sequences
        raise CompensatorError(f"{what} is not an array of numbers ({exc})") from None
    if array.dtype.kind not in "iuf":
        raise CompensatorError(f"{what} must hold real numbers (rad; N and N m for a wrench), got dtype {array.dtype}")
    return array.astype(np.float64, copy=False)


def _read_manifest(folder: Path) -> dict:
    """``folder/manifest.json``, checked against ``checksums.json`` and for the keys the runner reads."""
    path = folder / "manifest.json"
    if not path.is_file():
        raise CompensatorError(f"{folder}: no manifest.json (not an exported compensator folder)")
    data = path.read_bytes()
    checksums_path = folder / "checksums.json"
    try:
        checksums = json.loads(checksums_path.read_bytes())
    except FileNotFoundError:
        raise CompensatorError(f"{checksums_path}: missing; copy the exported folder whole (or export it again)") from None
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise CompensatorError(f"{checksums_path}: not valid JSON; copy the exported folder whole (or export it again)") from None
    files = checksums.get("files") if isinstance(checksums, dict) else None
    recorded = files.get("manifest.json") if isinstance(files, dict) else None
    if not isinstance(checksums, dict) or checksums.get("format") != CHECKSUMS_FORMAT or recorded is None:
        raise CompensatorError(f"{checksums_path}: not a {CHECKSUMS_FORMAT} file recording manifest.json")
    if hashlib.sha256(data).hexdigest() != recorded:
        raise CompensatorError(f"{path}: SHA-256 does not match checksums.json; the manifest was changed after export "
                               "(export again rather than edit it)")
    try:
        manifest = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CompensatorError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(manifest, dict):
        raise CompensatorError(f"{path}: not a JSON object")
    if manifest.get("format") != MANIFEST_FORMAT:
        raise CompensatorError(f"{path}: format {manifest.get('format')!r}, expected {MANIFEST_FORMAT!r}")
    n = manifest.get("n_joints")
    names = manifest.get("joint_names")
    problems = []
    if not isinstance(manifest.get("robot"), str):
        problems.append("robot must be a name")
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        problems.append(f"n_joints must be a whole number >= 1, got {n!r}")
    if not isinstance(names, list) or not all(isinstance(v, str) for v in names) or (isinstance(n, int) and len(names) != n):
        problems.append("joint_names must list n_joints names")
    problems += [f"{key} must be an object" for key in ("files", "sha256") if not isinstance(manifest.get(key), dict)]
    problems += [f"{key} must be an object" for key in ("outputs", "dtypes", "stages", "wrench")
                 if key in manifest and not isinstance(manifest[key], dict)]
    if problems:
        raise CompensatorError(f"{path}: " + "; ".join(problems))
    return manifest


def _joint_limits(manifest: dict, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(low, high)`` ``(N,)`` rad from ``joint_limits_rad`` (``null``: a continuous joint, unbounded;
    a manifest without the key: unbounded)."""
    n = manifest["n_joints"]
    low, high = np.full(n, -np.inf), np.full(n, np.inf)
    limits = manifest.get("joint_limits_rad")
    if limits is None:
        return low, high
    if not isinstance(limits, list) or len(limits) != n:
        raise CompensatorError(f"{path}: joint_limits_rad must list {n} [low, high] pairs (null for a continuous joint)")
    for j, pair in enumerate(limits):
        if pair is None:
            continue
        if (not isinstance(pair, list) or len(pair) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                                   for v in pair) or not pair[0] < pair[1]):
            raise CompensatorError(f"{path}: joint_limits_rad[{j}] must be [low, high] with low < high (rad), got {pair!r}")
        low[j], high[j] = pair
    return low, high
