"""The one registry of instruments: name -> subpackage, and which instrument a file belongs to.

Built-in instruments are listed in :data:`BUILTIN` (one line each); instruments of other
distributions register a subpackage under the entry-point group ``torchcal.instruments``
(``name = "package.subpackage"``). A subpackage exposes ``INSTRUMENT``, an
:class:`~torchcal.instruments.base.Instrument`. Subpackages are imported by name, on demand, so
that a command imports only the instrument its file needs and no instrument imports another.
"""

from __future__ import annotations

import importlib
from functools import cache
from importlib.metadata import entry_points
from pathlib import Path

from torchcal.core.errors import DataError, TorchcalError
from torchcal.data.csv_table import read_header
from torchcal.instruments.base import Instrument

#: Built-in instruments: registry name -> subpackage.
BUILTIN: dict[str, str] = {
    "tracker": "torchcal.instruments.tracker",
    "tracer": "torchcal.instruments.tracer",
    "stiffness": "torchcal.instruments.stiffness",
    "profile": "torchcal.instruments.profile",
    "sockets": "torchcal.instruments.sockets",
    "length_station": "torchcal.instruments.tracer.one_station",
}

ENTRY_POINT_GROUP = "torchcal.instruments"

#: The instrument of ``simulate`` without ``instrument=``, of ``torchcal run`` and of studies, and
#: whose options ``--help`` lists first.
DEFAULT = "tracker"


def default() -> Instrument:
    """The :data:`DEFAULT` instrument."""
    return get(DEFAULT)


@cache
def _modules() -> dict[str, str]:
    found = dict(BUILTIN)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(ep.name, ep.value)
    return found


def names() -> list[str]:
    """Registered instrument names, built-in first."""
    return list(_modules())


def get(name: str) -> Instrument:
    """The instrument registered as ``name``; a clear error for an unknown one."""
    modules = _modules()
    if name not in modules:
        raise TorchcalError(f"unknown instrument '{name}'; choose one of {', '.join(modules)}")
    instrument = importlib.import_module(modules[name]).INSTRUMENT
    if not isinstance(instrument, Instrument) or instrument.name != name:
        raise TorchcalError(f"{modules[name]}.INSTRUMENT is not an Instrument named '{name}'")
    return instrument


def recognise(path: str | Path) -> Instrument:
    """The instrument whose file ``path`` is, from its header: the most specific one that matches.

    Raises:
        DataError: no instrument recognises the columns (the message lists what each expects).
    """
    header = read_header(path)
    columns = set(header)
    matches = [inst for inst in map(get, names()) if inst.recognises(columns)]
    if not matches and len(header) == 1 and any(sep in header[0] for sep in ";\t"):
        sep = "semicolons" if ";" in header[0] else "tabs"
        raise DataError(f"the header is one column separated by {sep} ({header[0][:60]!r}): torchcal reads "
                        "comma-separated files with decimal points; save the file as CSV with ',' between "
                        "columns and '.' as the decimal mark", path=str(path), row=1)
    if not matches:
        expected = "; ".join(f"{', '.join(sorted(get(n).required_columns))} ({n})" for n in names())
        raise DataError(f"cannot tell the measurement kind from the header: expected {expected}",
                        path=str(path), row=1)
    most = max(len(inst.required_columns) for inst in matches)
    best = [inst for inst in matches if len(inst.required_columns) == most]
    if len(best) > 1:
        raise DataError(f"the header fits several instruments ({', '.join(i.name for i in best)}); "
                        "remove the columns of the others", path=str(path), row=1)
    return best[0]
