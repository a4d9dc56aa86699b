"""Output folders that are whole or absent: staged writes, a SHA-256 list, verification.

A model folder (``torchcal fit``) or an export folder (``torchcal export``) is one thing: its
files belong together. Two mechanisms keep it so:

* :func:`staged_folder` builds the new folder in a hidden sibling (``.<name>.staging-<pid>-*``)
  and, when the work has finished, swaps it into place in one ``renameat2(RENAME_EXCHANGE)``
  (Linux) or two renames elsewhere. A crash or ``kill -9`` at any moment leaves the earlier
  folder or the new one at the destination, never a mixture; an earlier folder's files never
  survive into the new one.
* Every file a writer puts into a folder is recorded with its SHA-256 in ``checksums.json``
  (:func:`write_member`). :func:`verify_folder` refuses a folder whose listed files are missing or
  changed, or that holds a model file nobody listed (a stale ``residual.safetensors``...), with
  one line naming the file and why.
"""

from __future__ import annotations

import ctypes
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from torchcal.core.errors import TorchcalError
from torchcal.core.hashing import sha256_bytes, sha256_file
from torchcal.core.io import atomic_write_bytes, atomic_write_json
from torchcal.core.outputs import claim_folder, stamp_folder

#: The list of a folder's files and their SHA-256 (hex).
CHECKSUMS = "checksums.json"
CHECKSUMS_FORMAT = "torchcal-checksums/1"

#: Files that mark a folder as torchcal output (one that a new result may replace).
MARKERS = (CHECKSUMS, "calibration.json", "sensor.json", "manifest.json")

#: Folder (next to ``report.md``) of the PNG figures a report links; a model folder does not list them.
FIGURES = "figures"

#: Suffixes of files that carry model content; such a file not listed in ``checksums.json`` is refused.
MEMBER_SUFFIXES = (".safetensors", ".json", ".yaml", ".yml", ".urdf", ".xml", ".onnx")

_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


class FolderError(TorchcalError):
    """An output folder is not whole, or an output path cannot be used; the message names the file."""


def _read_checksums(folder: Path) -> dict[str, str]:
    path = folder / CHECKSUMS
    if not path.is_file():
        return {}
    try:
        doc = json.loads(path.read_bytes().decode("utf-8"))
        files = doc["files"]
        if doc.get("format") != CHECKSUMS_FORMAT or not isinstance(files, dict):
            raise ValueError(f"format {doc.get('format')!r}")
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise FolderError(f"{path}: unreadable ({exc})") from None
    return {str(k): str(v) for k, v in files.items()}


def _write_checksums(folder: Path, files: dict[str, str]) -> None:
    atomic_write_json(folder / CHECKSUMS, {"format": CHECKSUMS_FORMAT, "algorithm": "sha256",
                                           "files": dict(sorted(files.items()))})


def write_member(folder: str | Path, name: str, data: bytes) -> Path:
    """Write ``folder/name`` atomically and record its SHA-256 in the folder's ``checksums.json``."""
    folder = Path(folder)
    atomic_write_bytes(folder / name, data)
    files = _read_checksums(folder)
    files[name] = sha256_bytes(data)
    _write_checksums(folder, files)
    return folder / name


def write_member_text(folder: str | Path, name: str, text: str) -> Path:
    """:func:`write_member` of UTF-8 text."""
    return write_member(folder, name, text.encode("utf-8"))


def write_member_json(folder: str | Path, name: str, obj: Any) -> Path:
    """:func:`write_member` of an indented JSON document."""
    return write_member_text(folder, name, json.dumps(obj, indent=2) + "\n")


def remove_member(folder: str | Path, name: str) -> None:
    """Delete ``folder/name`` (if present) and its entry in ``checksums.json``."""
    folder = Path(folder)
    files = _read_checksums(folder)
    if name in files:
        del files[name]
        _write_checksums(folder, files)
    (folder / name).unlink(missing_ok=True)


def seal(folder: str | Path) -> None:
    """Record every plain file of ``folder`` (hidden ones excepted) in ``checksums.json``."""
    folder = Path(folder)
    files = {p.name: sha256_file(p) for p in sorted(folder.iterdir())
             if p.is_file() and not p.name.startswith(".") and p.name != CHECKSUMS}
    _write_checksums(folder, files)


def verify_folder(folder: str | Path) -> None:
    """Refuse a folder that is not whole: each listed file present with its SHA-256, no unlisted model file.

    Raises:
        FolderError: one line naming the folder or the file and what is wrong with it.
    """
    folder = Path(folder)
    if not (folder / CHECKSUMS).is_file():
        raise FolderError(f"{folder}: no {CHECKSUMS}, so its files cannot be verified as one model "
                          "(an interrupted write, or written by an older torchcal): write it again")
    files = _read_checksums(folder)
    for name, digest in files.items():
        path = folder / name
        if Path(name).name != name or name.startswith("."):
            raise FolderError(f"{folder / CHECKSUMS}: lists {name!r}, which is not a file of this folder")
        if not path.is_file():
            raise FolderError(f"{path}: missing (listed in {CHECKSUMS})")
        if sha256_file(path) != digest:
            raise FolderError(f"{path}: SHA-256 differs from {CHECKSUMS} (changed or damaged after it was written)")
    for path in folder.iterdir():
        if (path.is_file() and not path.name.startswith(".") and path.name != CHECKSUMS
                and path.name not in files and path.suffix.lower() in MEMBER_SUFFIXES):
            raise FolderError(f"{path}: not listed in {CHECKSUMS} (left from another result or added later); "
                              "remove it or write the folder again")


def check_output_folder(dest: str | Path, what: str = "--out", purpose: str = "model",
                        within: tuple[str, ...] = ()) -> None:
    """Refuse, before any work, an output folder torchcal may not write for ``purpose``
    (:func:`torchcal.core.outputs.claim_folder`: absent, empty, or its own of the same purpose;
    inside another torchcal output only where that one's purpose is in ``within``)."""
    claim_folder(dest, purpose, what, within)
    dest = Path(dest)
    if purpose in ("model", "export"):
        foreign = [p.name for p in _unlisted(dest)]
        if foreign:
            raise FolderError(f"{dest / foreign[0]}: {what} would replace this folder, and torchcal did not write "
                              f"{', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}; move "
                              f"{'it' if len(foreign) == 1 else 'them'} out or give another folder")


def overlapping(a: str | Path, b: str | Path) -> bool:
    """Whether folders ``a`` and ``b`` are the same or one lies inside the other (resolved): writing
    one whole would replace or swallow the other."""
    a, b = Path(a).resolve(), Path(b).resolve()
    return a == b or a.is_relative_to(b) or b.is_relative_to(a)


def _unlisted(folder: Path) -> list[Path]:
    """The entries of a sealed ``folder`` its ``checksums.json`` does not list (its figures folder
    aside), sorted: a sealed folder lists every file torchcal wrote, so these are the user's own.
    ``[]`` for a folder without a checksum list."""
    if not (folder / CHECKSUMS).is_file():
        return []
    listed = _read_checksums(folder)
    return sorted(p for p in folder.iterdir() if not p.name.startswith(".") and p.name != CHECKSUMS
                  and p.name not in listed and not (p.is_dir() and p.name == FIGURES))


def refuse_foreign_entries(dest: Path, known: tuple[str, ...], sealed: tuple[str, ...] = (), what: str = "name=") -> None:
    """Refuse to replace a torchcal output folder ``dest`` (not sealed itself) that holds what torchcal did not write.

    ``known``: the names its own top level may hold; ``sealed``: its subfolders with their own
    ``checksums.json`` (a model), whose unlisted files are the user's.

    Raises:
        FolderError: naming the first foreign entry.
    """
    if not dest.is_dir():
        return
    foreign = [p for p in sorted(dest.iterdir()) if not p.name.startswith(".") and p.name not in known]
    for name in sealed:
        foreign += _unlisted(dest / name)
    if foreign:
        raise FolderError(f"{foreign[0]}: {what} would replace {dest}, and torchcal did not write this; move it out or "
                          "give another name")


def _exchange(a: Path, b: Path) -> bool:
    """Swap the directory entries ``a`` and ``b`` atomically; ``False`` where the system cannot."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (22, 38, 95):  # EINVAL, ENOSYS, EOPNOTSUPP: no exchange here; fall back
        return False
    raise OSError(err, os.strerror(err), str(b))


def _fsync_tree(folder: Path) -> None:
    for path in folder.iterdir():
        if path.is_file():
            with open(path, "rb") as handle:
                os.fsync(handle.fileno())
    _fsync_dir(folder)


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _remove_dead_stagings(dest: Path) -> None:
    """Delete staging folders of ``dest`` left by processes that no longer run (killed mid-write)."""
    prefix = f".{dest.name}.staging-"
    for path in dest.parent.glob(prefix + "*"):
        pid = path.name[len(prefix):].split("-", 1)[0]
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            shutil.rmtree(path, ignore_errors=True)
        except OSError:
            pass


def _swap_in(staging: Path, dest: Path, prefix: str) -> None:
    """Put the complete folder ``staging`` at ``dest``, atomically where the system can exchange
    the two, and delete the earlier ``dest``."""
    if dest.is_dir() and _exchange(staging, dest):
        _fsync_dir(dest.parent)
        shutil.rmtree(staging, ignore_errors=True)  # now the earlier folder
        return
    if dest.is_dir():
        old = Path(tempfile.mkdtemp(dir=dest.parent, prefix=prefix + "old-"))
        os.rename(dest, old / dest.name)
        os.rename(staging, dest)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(staging, dest)
    _fsync_dir(dest.parent)


@contextmanager
def deferred_folder(dest: str | Path, what: str = "--out", purpose: str = "export") -> Iterator[tuple[Path, Callable[[], None]]]:
    """A hidden sibling of ``dest`` for a writer that builds a whole folder (itself staged), moved to
    ``dest`` only by the ``commit`` it yields: after the outputs it belongs with are in place.

    Yields ``(pending, commit)``. Without ``commit`` (an error, an interrupt) ``pending`` is deleted
    and ``dest`` is untouched; a killed process's ``pending`` is deleted by the next writer of ``dest``.
    """
    dest = Path(dest)
    check_output_folder(dest, what, purpose)
    dest.parent.mkdir(parents=True, exist_ok=True)
    _remove_dead_stagings(dest)
    prefix = f".{dest.name}.staging-{os.getpid()}-"
    pending = dest.parent / f"{prefix}pending"
    shutil.rmtree(pending, ignore_errors=True)
    committed = False

    def commit() -> None:
        nonlocal committed
        _fsync_tree(pending)
        _swap_in(pending, dest, prefix)
        committed = True

    try:
        yield pending, commit
    finally:
        if not committed:
            shutil.rmtree(pending, ignore_errors=True)


@contextmanager
def staged_folder(dest: str | Path, what: str = "--out", purpose: str = "model", sealed: bool = True,
                  within: tuple[str, ...] = ()) -> Iterator[Path]:
    """Build a folder in a hidden sibling of ``dest`` and swap it into place when the block ends.

    Yields the staging folder (stamped with ``purpose``, :mod:`torchcal.core.outputs`). On a normal
    exit its files are sealed (:func:`seal` of files no writer recorded; not when ``sealed`` is
    false: a report or twin folder has no checksum list), flushed to disk and the folder replaces ``dest`` atomically (the
    earlier ``dest`` is then deleted). On an exception, ``KeyboardInterrupt`` included, the
    staging folder is deleted and ``dest`` is untouched.
    """
    dest = Path(dest)
    check_output_folder(dest, what, purpose, within)
    dest.parent.mkdir(parents=True, exist_ok=True)
    _remove_dead_stagings(dest)
    prefix = f".{dest.name}.staging-{os.getpid()}-"
    try:
        # made inside the try: a Ctrl-C that lands just after mkdtemp is cleaned up below too
        staging = Path(tempfile.mkdtemp(dir=dest.parent, prefix=prefix))
        os.chmod(staging, 0o755)
        stamp_folder(staging, purpose)
        yield staging
        if sealed:
            listed = _read_checksums(staging)
            unlisted = [p for p in staging.iterdir() if p.is_file() and not p.name.startswith(".")
                        and p.name != CHECKSUMS and p.name not in listed]
            if unlisted or not listed:
                seal(staging)
        _fsync_tree(staging)
        _swap_in(staging, dest, prefix)
    except BaseException:
        # this process's staging folders, also one whose name an interrupt kept from ``staging``;
        # never the "-old-" folder that may hold the earlier ``dest`` while it is being replaced
        for leftover in dest.parent.glob(prefix + "*"):
            if not leftover.name.startswith(prefix + "old-"):
                shutil.rmtree(leftover, ignore_errors=True)
        raise
