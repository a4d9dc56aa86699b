"""No module outside ``torchcal/instruments`` names an instrument in code: they reach instruments through
the protocol and the registry only (the import half is also an import-linter contract)."""

from __future__ import annotations

import ast
from pathlib import Path

import torchcal
from torchcal.instruments.registry import BUILTIN

PACKAGE = Path(torchcal.__file__).parent
#: Words that are an instrument's name and also the name of something shared: the model stage a
#: stiffness fit adds (``stages``, ``compensate``) and the ``torchcal.stiffness`` layer.
SHARED_WORDS = {"stiffness"}


def _docstrings(tree: ast.AST) -> set[int]:
    """ids of the docstring constants of ``tree`` (prose, not code)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                found.add(id(first.value))
    return found


def named_instruments(path: Path) -> list[str]:
    """``file:line: text`` of each place in ``path``'s code that names a built-in instrument."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    prose = _docstrings(tree)
    names = set(BUILTIN)
    hits = []
    for node in ast.walk(tree):
        text = None
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in prose:
            value = node.value
            if (value in names - SHARED_WORDS or any(f"instruments.{n}" in value or f"instrument={n}" in value
                                                     for n in names)):
                text = value
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            modules = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            text = next((m for m in modules for n in names if m.startswith(f"torchcal.instruments.{n}")), None)
        if text is not None:
            hits.append(f"{path.name}:{node.lineno}: {text!r}")
    return hits


def test_no_module_outside_instruments_names_one():
    outside = [p for p in PACKAGE.rglob("*.py") if "instruments" not in p.relative_to(PACKAGE).parts]
    assert len(outside) > 100  # the walk found the package
    hits = [hit for path in sorted(outside) for hit in named_instruments(path)]
    assert not hits, "\n".join(hits)


def test_the_check_finds_a_named_instrument(tmp_path):
    # the check itself can fail: an import, a name in a string, a name inside an override
    sample = tmp_path / "sample.py"
    sample.write_text('"""Prose may say tracker."""\nimport torchcal.instruments.tracer\n'
                      'KIND = "profile"\nARGS = ["instrument=sockets"]\nSTAGE = "stiffness"\n', encoding="utf-8")
    hits = named_instruments(sample)
    assert [h.split(":")[1] for h in hits] == ["2", "3", "4"]
