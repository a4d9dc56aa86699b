"""One rule for every output path: torchcal replaces only what it wrote itself, for the same purpose.

A model folder holds hours of tracker time; an export folder is what a controller runs. So a
command may write to an output path only when the path

* does not exist, or is an empty folder; or
* is what torchcal wrote earlier **for the same purpose** (a model folder for ``fit --out``, an
  export folder for ``export --out``, a report folder for ``--report``, a metrics file for
  ``--json``...);

and it never lies inside another torchcal output folder (``--json`` into a model folder, a report
inside an export). Anything else is refused with one line, before any work, naming what the path
holds (:class:`OutputClaimError`, exit status 2).

Folders torchcal writes carry a hidden stamp ``.torchcal-output`` (``{"purpose": ...}``); folders
written before the stamp existed are recognised by their marker files (``calibration.json``,
``manifest.json``, ``truth.json``...). Files carry their purpose inside: a metrics JSON has the key
``torchcal_output``; a CSV is recognised by its exact header.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

from torchcal.core.errors import TorchcalError
from torchcal.core.io import atomic_write_text

#: The hidden file naming a folder's purpose.
STAMP = ".torchcal-output"

#: Folder purposes and what they are called in messages.
FOLDER_PURPOSES = {
    "model": "a model folder",
    "export": "an export folder",
    "twin": "a twin case folder",
    "report": "a report folder",
    "run": "a run folder",
    "study": "a study folder",
}

#: Marker files of folders written before the stamp (first match wins).
_LEGACY_MARKERS = (
    ("calibration.json", "model"),
    ("sensor.json", "model"),
    ("manifest.json", "export"),
    ("truth.json", "twin"),
    ("study.db", "study"),
    ("motion.json", "report"),
    ("report.html", "report"),
    ("metrics.json", "run"),
)

#: Key a metrics JSON file carries with its purpose.
JSON_KEY = "torchcal_output"


class OutputClaimError(TorchcalError):
    """An output path holds something torchcal did not write for this purpose; nothing was written."""


def stamp_folder(folder: str | Path, purpose: str) -> None:
    """Mark ``folder`` as torchcal output of ``purpose`` (hidden, so checksums and listings skip it)."""
    if purpose not in FOLDER_PURPOSES:
        raise ValueError(f"unknown output purpose {purpose!r}")
    atomic_write_text(Path(folder) / STAMP, json.dumps({"purpose": purpose}) + "\n")


def folder_purpose(folder: str | Path) -> str | None:
    """The purpose of a torchcal output folder (stamp, else marker files); ``None`` if it is none."""
    folder = Path(folder)
    stamp = folder / STAMP
    if stamp.is_file():
        try:
            purpose = json.loads(stamp.read_text(encoding="utf-8")).get("purpose")
        except (ValueError, OSError, AttributeError):
            purpose = None
        if purpose in FOLDER_PURPOSES:
            return str(purpose)
    for marker, purpose in _LEGACY_MARKERS:
        if (folder / marker).is_file():
            return purpose
    return None


def _enclosing_output(path: Path) -> tuple[Path, str] | None:
    """The nearest folder above ``path`` that is torchcal output, with its purpose."""
    for parent in path.resolve().parents:
        purpose = folder_purpose(parent) if parent.is_dir() else None
        if purpose is not None:
            return parent, purpose
    return None


def _check_parent(path: Path, what: str) -> None:
    parent = path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise OutputClaimError(f"{parent}: a file stands where {what} needs a folder")
    if not os.access(parent, os.W_OK):
        raise OutputClaimError(f"{parent}: not writable")


def refuse_inside_output(path: str | Path, what: str, within: tuple[str, ...] = ()) -> None:
    """Refuse an output path inside a torchcal output folder (a model, an export, a run), whose
    files that folder's checksums own; inside one whose purpose is in ``within`` it is allowed (a
    study's own storage in its folder).

    Raises:
        OutputClaimError: one line naming the path and the folder.
    """
    _refuse_inside(Path(path), what, within)


def _refuse_inside(path: Path, what: str, within: tuple[str, ...] = ()) -> None:
    enclosing = _enclosing_output(path)
    if enclosing is not None and enclosing[1] not in within:
        folder, theirs = enclosing
        raise OutputClaimError(f"{path}: {what} lies inside {FOLDER_PURPOSES[theirs]} ({folder}), whose files "
                               f"belong to it; give a path outside it")


def claim_folder(dest: str | Path, purpose: str, what: str = "--out", within: tuple[str, ...] = ()) -> None:
    """Refuse, before any work, an output folder that torchcal may not (re)write for ``purpose``.

    Accepted: an absent path, an empty folder, or a folder torchcal wrote for ``purpose``; inside
    another torchcal output folder only where its purpose is one of ``within`` (a study's best run).

    Raises:
        OutputClaimError: one line naming the path and what it holds.
    """
    dest = Path(dest)
    name = FOLDER_PURPOSES[purpose]
    if dest.exists() and not dest.is_dir():
        raise OutputClaimError(f"{dest}: {what} names an existing file; give a folder")
    _refuse_inside(dest, what, within)
    if dest.is_dir() and any(dest.iterdir()):
        theirs = folder_purpose(dest)
        if theirs is None:
            raise OutputClaimError(f"{dest}: {what} names a folder that holds other files (not a torchcal output); "
                                   "give a new or empty folder")
        if theirs != purpose:
            raise OutputClaimError(f"{dest}: {what} names {FOLDER_PURPOSES[theirs]}, and this command replaces only "
                                   f"{name}: give another folder")
    _check_parent(dest, what)


def claim_file(path: str | Path, purpose: str, what: str, recognise: Callable[[Path], bool]) -> None:
    """Refuse, before any work, an output file torchcal may not (re)write for ``purpose``.

    Accepted: an absent path, or a file that ``recognise`` says torchcal wrote for ``purpose``;
    never a path inside a torchcal output folder.

    Raises:
        OutputClaimError: one line naming the path and what it holds.
    """
    path = Path(path)
    if path.is_dir():
        raise OutputClaimError(f"{path}: {what} names an existing folder; give a file name")
    _refuse_inside(path, what)
    if path.exists() and not recognise(path):
        raise OutputClaimError(f"{path}: {what} names an existing file that is not a {purpose} file torchcal wrote; "
                               "give a new file name (torchcal replaces only its own)")
    _check_parent(path, what)


def check_name(value: str, what: str) -> str:
    """``value`` as one folder name (a run or study name): refused if it could leave its folder.

    Letters, digits, ``.``, ``_``, ``-`` and ``+``; at most 100 characters; not ``.`` or ``..``.
    """
    text = str(value)
    if (not text or len(text) > 100 or text in (".", "..") or text.startswith(".")
            or any(not (c.isascii() and (c.isalnum() or c in "._-+")) for c in text)):
        shown = text if len(text) <= 60 else text[:57] + "..."
        raise OutputClaimError(f"{what} {shown!r}: a name is one folder name of at most 100 letters, digits, "
                               "'.', '_', '-' or '+', not starting with '.' (no '/', no '..')")
    return text


def json_of(purpose: str) -> Callable[[Path], bool]:
    """A recogniser of JSON objects that carry ``torchcal_output: <purpose>`` (``metrics``, ``check``...)."""
    def recognise(path: Path) -> bool:
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (ValueError, OSError):
            return False
        return isinstance(doc, dict) and doc.get(JSON_KEY) == purpose
    return recognise


#: What ``evaluate --json`` writes.
is_metrics_json = json_of("metrics")


def csv_with_header(header: Callable[[list[str]], bool]) -> Callable[[Path], bool]:
    """A recogniser of CSV files whose first line ``header`` accepts (split at commas)."""
    def recognise(path: Path) -> bool:
        try:
            with path.open(encoding="utf-8") as handle:
                first = handle.readline().strip()
        except (OSError, UnicodeDecodeError):
            return False
        return header([c.strip() for c in first.split(",")])
    return recognise
