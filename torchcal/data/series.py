"""Several measurement series of one robot pooled into one set (each series keeps its index).

A series is one file: one instrument placement (its own frame) and possibly its own tool mount.
The pooled set carries ``series`` (the index of each pose's file, in the order given), so that the
folds of every choice keep each series' regions and measurement order apart
(:func:`torchcal.data.folds.make_folds`) and the fit registers a frame per series
(:mod:`torchcal.stages.series`).
"""

from __future__ import annotations

import hashlib

import torch

from torchcal.core.errors import DataError
from torchcal.data.measurements import Measurements


def pool_series(series: list[Measurements]) -> Measurements:
    """The poses of every series in one set, in the order given; ``series`` holds each pose's file index.

    Positions stay in each series' own instrument frame (aligning them is the fit's job). Line
    numbers are each file's own; the pooled ``sha256`` is that of the files' digests in order.

    Raises:
        DataError: no series, or series that disagree in joint count or in which optional columns they have.
    """
    if not series:
        raise DataError("no measurement series given")
    refuse_repeated_series(series)
    first = series[0]
    for other in series[1:]:
        if other.q.shape[1] != first.q.shape[1]:
            raise DataError(f"{other.q.shape[1]} joints, but {first.source} has {first.q.shape[1]}", path=other.source)
        for name in ("rotation", "wrench", "temperature"):
            if (getattr(other, name) is None) != (getattr(first, name) is None):
                has, lacks = (first, other) if getattr(other, name) is None else (other, first)
                raise DataError(f"series differ in their columns: {has.source} has {name}, {lacks.source} does not; "
                                "pool files with the same columns", path=other.source)

    def cat(name: str) -> torch.Tensor | None:
        parts = [getattr(s, name) for s in series]
        return None if parts[0] is None else torch.cat(parts)

    digest = hashlib.sha256("".join(s.sha256 for s in series).encode()).hexdigest()
    index = torch.cat([torch.full((len(s),), i, dtype=torch.long) for i, s in enumerate(series)])
    return Measurements(
        q=torch.cat([s.q for s in series]), position=torch.cat([s.position for s in series]),
        rotation=cat("rotation"), wrench=cat("wrench"), temperature=cat("temperature"),
        source=" + ".join(s.source for s in series),
        line_numbers=tuple(line for s in series for line in s.line_numbers), sha256=digest, series=index,
    )


def refuse_repeated_series(series: list[Measurements]) -> None:
    """Refuse a file given twice (the same content), or a row copied from one series into another.

    Pooled copies would count the same measurements twice: the fit's uncertainty and its few-poses
    warnings would claim twice the evidence there is.

    Raises:
        DataError: naming the file, the row and where its copy lies.
    """
    seen_files: dict[str, str] = {}
    seen_rows: dict[bytes, tuple[str, int]] = {}
    for s in series:
        if s.sha256 and s.sha256 in seen_files:  # an empty digest: a set made in memory, not read from a file
            raise DataError(f"has the same content as {seen_files[s.sha256]}: one series given twice", path=s.source)
        seen_files[s.sha256] = s.source
        rows = torch.cat([s.q, s.position], 1).to(torch.float64).numpy()
        own: dict[bytes, tuple[str, int]] = {}
        for row, line in zip(rows, s.line_numbers or range(2, len(rows) + 2)):
            key = row.tobytes()
            if key in seen_rows:
                source, first_line = seen_rows[key]
                raise DataError(f"copies row {first_line} of {source} exactly (same joints and same measurement): a row "
                                "of one series pasted into another", path=s.source, row=line)
            own[key] = (s.source, line)
        seen_rows.update(own)


def split_series(data: Measurements) -> list[Measurements]:
    """The series of a pooled set, in index order (``[data]`` for a single series)."""
    if data.series is None:
        return [data]
    return [data.subset(torch.nonzero(data.series == i).squeeze(-1)) for i in range(int(data.series.max()) + 1)]


def series_count(data: Measurements) -> int:
    """How many series ``data`` pools (1 for a plain file)."""
    return 1 if data.series is None else int(data.series.max()) + 1
