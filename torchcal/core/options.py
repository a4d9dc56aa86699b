"""The ``key=value`` options of a configuration dataclass, listed from the class itself.

``torchcal <command> --help`` prints these, so the help cannot drift from what the command
accepts: every field (nested dataclasses flattened to dotted keys) with its default and the first
sentence of its description in the class's ``Attributes:`` docstring section.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import re
import shutil
import textwrap
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Option:
    """One ``key=value`` option: its dotted key, default (as the command line writes it) and help."""

    key: str
    default: str
    help: str


_ENTRY = re.compile(r"^(?P<indent>\s+)(?P<names>[A-Za-z_][\w ,/]*?):\s+(?P<text>.*)$")


def attribute_docs(cls: type) -> dict[str, str]:
    """Field name -> description, from the ``Attributes:`` section of ``cls``'s docstring (and its bases')."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        doc = inspect.getdoc(klass) if klass.__doc__ else None
        if not doc or "Attributes:" not in doc:
            continue
        section = doc.split("Attributes:", 1)[1].splitlines()
        current: list[str] = []
        text: list[str] = []
        base_indent: int | None = None
        for line in [*section, ""]:
            if not line.strip() and base_indent is not None and not text:
                continue
            match = _ENTRY.match(line)
            indent = len(line) - len(line.lstrip())
            if match and (base_indent is None or indent == base_indent):
                for name in current:
                    docs[name] = " ".join(text)
                base_indent = indent
                current = [n.strip() for n in re.split(r"\s*/\s*|\s*,\s*", match["names"]) if n.strip()]
                text = [match["text"].strip()]
            elif line.strip() and base_indent is not None and indent > base_indent:
                text.append(line.strip())
            elif base_indent is not None:
                for name in current:
                    docs[name] = " ".join(text)
                current, text = [], []
                if line.strip():
                    break
    return docs


def _plain(text: str) -> str:
    """Docstring markup as plain text: ``x`` -> x, :mod:`~a.b` -> b, :func:`a.b` -> a.b."""
    text = re.sub(r":\w+:`~[\w.]*?\.?(\w+)`", r"\1", text)
    text = re.sub(r":\w+:`([^`]+)`", r"\1", text)
    return text.replace("``", "")


def _description(text: str) -> str:
    """The whole attribute description as plain text (every choice of an option must stay readable)."""
    return " ".join(_plain(text).split())


def _default(field: dataclasses.Field) -> Any:
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return None


def _render(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple, dict)):  # as an override writes it: key=[1,2] (no spaces)
        return json.dumps(value, separators=(",", ":"), default=str)
    return str(value)


def list_options(config: Any, prefix: str = "") -> list[Option]:
    """Every option of a configuration dataclass (nested dataclasses as dotted keys), in field order.

    ``config`` is the class (defaults from its fields) or an instance (defaults are its values:
    a configuration composed from ``configs/`` shows what a run would really use).
    """
    cls = config if isinstance(config, type) else type(config)
    docs = attribute_docs(cls)
    out: list[Option] = []
    for field in dataclasses.fields(cls):
        value = _default(field) if isinstance(config, type) else getattr(config, field.name)
        key = f"{prefix}{field.name}"
        if dataclasses.is_dataclass(value):
            out += list_options(value, prefix=f"{key}.")
            continue
        out.append(Option(key, _render(value), _description(docs.get(field.name, ""))))
    return out


def format_options(title: str, options: list[Option], width: int | None = None) -> str:
    """A help block: ``title`` and per option ``key=default  help``, the help wrapped to ``width``
    columns (default: the terminal's, at least 80) under its own column."""
    if not options:
        return ""
    width = width or max(80, shutil.get_terminal_size((100, 24)).columns)
    keys = [f"{o.key}={o.default}" for o in options]
    pad = min(max(len(k) for k in keys), 44) + 2
    indent = " " * (pad + 2)
    lines = [title]
    for key, option in zip(keys, options):
        if len(key) <= pad - 2:
            lines.append(textwrap.fill(option.help, width=width, initial_indent=f"  {key}".ljust(pad + 2),
                                       subsequent_indent=indent) if option.help else f"  {key}")
        else:
            lines.append(f"  {key}")
            if option.help:
                lines.append(textwrap.fill(option.help, width=width, initial_indent=indent, subsequent_indent=indent))
    return "\n".join(lines)
