"""Exceptions that the command line turns into one clear line instead of a traceback."""

from __future__ import annotations


class TorchcalError(Exception):
    """Base class of every error torchcal reports to a user."""


class DataError(TorchcalError, ValueError):
    """A measurement file is malformed; the message names the file, row and column."""

    def __init__(
        self,
        message: str,
        *,
        path: str | None = None,
        row: int | None = None,
        column: str | None = None,
    ) -> None:
        self.path, self.row, self.column = path, row, column
        where = []
        if path is not None:
            where.append(str(path))
        if row is not None:
            where.append(f"row {row}")
        if column is not None:
            where.append(f"column '{column}'")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class ModelError(TorchcalError, ValueError):
    """A robot description (YAML or URDF) is invalid or does not match the data."""


class IdentifiabilityWarning(UserWarning):
    """The data cannot separate some parameters; the message names them."""
