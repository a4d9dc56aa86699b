"""Option listing read from a dataclass: every field, nested keys dotted, defaults and first sentences of the docs."""

from __future__ import annotations

from dataclasses import dataclass, field

from torchcal.core.options import attribute_docs, list_options


@dataclass
class _Inner:
    """Inner settings.

    Attributes:
        steps: iterations (at most ``max``; see :func:`~torchcal.identify.lm.solve`). More text.
    """

    steps: int = 4


@dataclass
class _Settings:
    """Settings.

    Attributes:
        low / high: the range, mm; the second sentence is left out.
        flag: a switch that spans
            two lines.
        inner: nested settings.
        items: a list.
    """

    low: float = 0.5
    high: float = 2.0
    flag: bool = False
    inner: _Inner = field(default_factory=_Inner)
    items: list[int] = field(default_factory=lambda: [1, 2])


def test_attribute_docs_read_shared_and_continued_entries():
    docs = attribute_docs(_Settings)
    assert docs["low"] == docs["high"] == "the range, mm; the second sentence is left out."
    assert docs["flag"] == "a switch that spans two lines."


def test_options_cover_every_field_with_defaults_as_an_override_writes_them():
    options = {o.key: o for o in list_options(_Settings)}
    assert list(options) == ["low", "high", "flag", "inner.steps", "items"]
    assert [options[k].default for k in options] == ["0.5", "2", "false", "4", "[1,2]"]
    # the whole description: every choice of an option stays readable in --help
    assert options["low"].help == "the range, mm; the second sentence is left out."
    assert options["inner.steps"].help.startswith("iterations (at most max; see solve)")


def test_help_blocks_wrap_long_descriptions_without_cutting_them():
    from torchcal.core.options import Option, format_options

    text = "choices: " + ", ".join(f"choice{i} (what it does)" for i in range(30))
    block = format_options("title", [Option("key", "auto", text)], width=90)
    assert all(len(line) <= 90 for line in block.splitlines())
    assert "choice29 (what it does)" in block and "..." not in block


def test_an_instance_lists_its_own_values():
    options = {o.key: o.default for o in list_options(_Settings(low=0.1, inner=_Inner(steps=9)))}
    assert options["low"] == "0.1" and options["inner.steps"] == "9"
