"""Exceptions that the command line turns into one clear line instead of a traceback."""

from __future__ import annotations

from collections.abc import Iterable


def did_you_mean(word: object, options: Iterable[str], prefix: str = "") -> str:
    """`` (did you mean 'x'?)`` for the option closest to a misspelt ``word`` (``prefix`` written
    before it), else ``""``: a message's hint for an unknown key, option or name."""
    import difflib

    match = difflib.get_close_matches(str(word), list(options), n=1, cutoff=0.6)
    return f" (did you mean '{prefix}{match[0]}'?)" if match else ""


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
