"""Joint trajectories at a control rate, and their CSV / NumPy files.

CSV layout (header row, one control cycle per row): ``t`` (s), ``q1..qN`` and ``qd1..qdN``
(deg and deg/s by default, rad and rad/s with ``angle_unit="rad"``), the joint naming of the
measurement contract. Files are written atomically (temporary file in the same folder, then
``os.replace``), so a controller polling the file never reads half of it.
"""

from __future__ import annotations

import csv
import io
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchcal.core.errors import DataError

_ANGLE = {"deg": 180.0 / math.pi, "rad": 1.0}


@dataclass(frozen=True)
class JointTrajectory:
    """Joint positions and velocities at a fixed control rate (SI inside).

    Attributes:
        t: ``(K,)`` sample times, s.
        q: ``(..., K, N)`` joint positions, rad.
        qdot: ``(..., K, N)`` joint velocities held from ``t[k]`` to ``t[k+1]``, rad/s.
        rate_hz: control rate, Hz.
    """

    t: torch.Tensor
    q: torch.Tensor
    qdot: torch.Tensor
    rate_hz: float

    @property
    def dof(self) -> int:
        return int(self.q.shape[-1])

    def to_numpy(self) -> dict[str, np.ndarray]:
        """``{"t", "q", "qdot"}`` as NumPy arrays (s, rad, rad/s)."""
        return {"t": self.t.cpu().numpy(), "q": self.q.cpu().numpy(), "qdot": self.qdot.cpu().numpy()}

    def save_npz(self, path: str | Path) -> Path:
        """Write ``t, q, qdot, rate_hz`` (SI) to a ``.npz`` file, atomically."""
        buffer = io.BytesIO()
        arrays = self.to_numpy()
        np.savez(buffer, rate_hz=np.float64(self.rate_hz), t=arrays["t"], q=arrays["q"], qdot=arrays["qdot"])
        return _atomic_write(Path(path), buffer.getvalue())

    def save_csv(self, path: str | Path, angle_unit: str = "deg") -> Path:
        """Write the trajectory as CSV (see module docstring); only an unbatched ``(K, N)`` one."""
        if self.q.dim() != 2:
            raise DataError(f"CSV holds one trajectory; got q of shape {tuple(self.q.shape)}", path=str(path))
        if angle_unit not in _ANGLE:
            raise DataError(f"angle_unit {angle_unit!r} is not one of {sorted(_ANGLE)}", path=str(path))
        scale = _ANGLE[angle_unit]
        n = self.dof
        text = io.StringIO()
        writer = csv.writer(text, lineterminator="\n")
        writer.writerow(["t"] + [f"q{i}" for i in range(1, n + 1)] + [f"qd{i}" for i in range(1, n + 1)])
        rows = torch.cat([self.t.unsqueeze(-1), self.q * scale, self.qdot * scale], -1).cpu().tolist()
        writer.writerows([[repr(v) for v in row] for row in rows])
        return _atomic_write(Path(path), text.getvalue().encode())


def load_csv(path: str | Path, angle_unit: str = "deg", device: str | torch.device = "cpu") -> JointTrajectory:
    """Read a trajectory CSV written by :meth:`JointTrajectory.save_csv`."""
    path = Path(path)
    if angle_unit not in _ANGLE:
        raise DataError(f"angle_unit {angle_unit!r} is not one of {sorted(_ANGLE)}", path=str(path))
    if not path.is_file():
        raise DataError("trajectory file not found", path=str(path))
    with path.open(newline="") as handle:
        reader = csv.reader(handle)
        header = next(reader, None)
        if not header or header[0] != "t" or (len(header) - 1) % 2:
            raise DataError("header must be t, q1..qN, qd1..qdN", path=str(path), row=1)
        n = (len(header) - 1) // 2
        expected = ["t"] + [f"q{i}" for i in range(1, n + 1)] + [f"qd{i}" for i in range(1, n + 1)]
        if header != expected:
            raise DataError(f"header must be {','.join(expected)}", path=str(path), row=1)
        values = []
        for row_no, row in enumerate(reader, start=2):
            if len(row) != len(header):
                raise DataError(f"expected {len(header)} fields, got {len(row)}", path=str(path), row=row_no)
            try:
                values.append([float(v) for v in row])
            except ValueError:
                bad = next(i for i, v in enumerate(row) if not _is_float(v))
                raise DataError(f"not a number: {row[bad]!r}", path=str(path), row=row_no, column=header[bad]) from None
    if len(values) < 2:
        raise DataError("a trajectory needs at least 2 rows", path=str(path))
    data = torch.tensor(values, dtype=torch.float64, device=device)
    t = data[:, 0]
    steps = torch.diff(t)
    if not bool((steps > 0).all()):
        raise DataError("column 't' must increase strictly", path=str(path), column="t")
    scale = _ANGLE[angle_unit]
    return JointTrajectory(t=t, q=data[:, 1 : n + 1] / scale, qdot=data[:, n + 1 :] / scale, rate_hz=float(1.0 / steps.mean()))


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _atomic_write(path: Path, payload: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(payload)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
