"""A report as section objects, rendered to Markdown and to one self-contained HTML page.

Both renderings come from the same :class:`Report`: the Markdown links each figure as a PNG file
next to it, the HTML carries the same PNG inline as a base64 ``data:`` URI and its own ``<style>``
(no external file, no script), so ``report.html`` can be mailed or archived alone. Text blocks
are plain text (no Markup is interpreted); the HTML escapes it.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from torchcal.core.folder import FIGURES, write_member_text
from torchcal.core.io import atomic_write_bytes, atomic_write_text
from torchcal.core.workers import side_by_side


@dataclass(frozen=True)
class Paragraph:
    """Plain text; blank lines are not expected inside (one paragraph)."""

    text: str


@dataclass(frozen=True)
class Table:
    """A table with a header row; ``name`` identifies it in the HTML (``data-table``) for checks."""

    name: str
    columns: list[str]
    rows: list[list[str]]
    caption: str = ""


@dataclass(frozen=True)
class Figure:
    """A PNG figure; ``name`` is its file stem under :data:`FIGURES`."""

    name: str
    png: bytes
    caption: str


@dataclass(frozen=True)
class PendingFigure:
    """A figure still to be drawn: ``draw(*args)`` returns its PNG bytes.

    ``draw`` is a pure function of its arguments (those of :mod:`torchcal.report.plots`), so the
    figures of a report can be drawn side by side in worker processes (:func:`draw_figures`).
    """

    name: str
    draw: Callable[..., bytes]
    args: tuple
    caption: str


@dataclass(frozen=True)
class Preformatted:
    """Fixed-width text kept as it is (console tables, identifiability summaries)."""

    text: str


Block = Paragraph | Table | Figure | PendingFigure | Preformatted


@dataclass
class Section:
    heading: str
    blocks: list[Block] = field(default_factory=list)


@dataclass
class Report:
    title: str
    sections: list[Section] = field(default_factory=list)

    def figures(self) -> list[Figure]:
        return [b for s in self.sections for b in s.blocks if isinstance(b, Figure)]

    def tables(self) -> list[Table]:
        return [b for s in self.sections for b in s.blocks if isinstance(b, Table)]


def draw_figures(report: Report, jobs: int = 1) -> Report:
    """``report`` with its :class:`PendingFigure` blocks drawn, shared between this process and up to
    ``jobs - 1`` ready workers (:func:`torchcal.core.workers.side_by_side`: the same bytes either way)."""
    pending = [b for s in report.sections for b in s.blocks if isinstance(b, PendingFigure)]
    if not pending:
        return report
    drawn = dict(zip(map(id, pending), side_by_side(_draw, [(p.draw, p.args) for p in pending], jobs)))

    def block(b: Block) -> Block:
        return Figure(b.name, drawn[id(b)], b.caption) if isinstance(b, PendingFigure) else b

    return Report(report.title, [Section(s.heading, [block(b) for b in s.blocks]) for s in report.sections])


def _draw(draw: Callable[..., bytes], args: tuple) -> bytes:
    return draw(*args)


def _md_cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def to_markdown(report: Report) -> str:
    """The Markdown page; figures are linked as ``figures/<name>.png`` (drawn or still pending)."""
    out = [f"# {report.title}", ""]
    for section in report.sections:
        out += [f"## {section.heading}", ""]
        for block in section.blocks:
            if isinstance(block, Paragraph):
                out += [block.text.strip(), ""]
            elif isinstance(block, Preformatted):
                out += ["```", block.text.rstrip(), "```", ""]
            elif isinstance(block, Figure | PendingFigure):
                out += [f"![{block.caption}]({FIGURES}/{block.name}.png)", "", f"*{block.caption}*", ""]
            elif isinstance(block, Table):
                if block.caption:
                    out += [block.caption, ""]
                out.append("| " + " | ".join(_md_cell(c) for c in block.columns) + " |")
                out.append("|" + "---|" * len(block.columns))
                out += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in block.rows]
                out.append("")
    return "\n".join(out)


_STYLE = """
body { font-family: system-ui, sans-serif; max-width: 68rem; margin: 1.5rem auto; padding: 0 1rem; color: #222; }
h1 { font-size: 1.6rem; } h2 { font-size: 1.25rem; margin-top: 2rem; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.6rem 0 1rem; font-size: 0.88rem; }
th, td { border: 1px solid #ccc; padding: 0.2rem 0.5rem; text-align: left; vertical-align: top; }
th { background: #f0f0f0; } caption { caption-side: top; text-align: left; padding: 0.2rem 0; }
td.n { text-align: right; font-variant-numeric: tabular-nums; }
pre { background: #f6f6f6; padding: 0.6rem; overflow-x: auto; font-size: 0.82rem; }
figure { margin: 0.8rem 0 1.2rem; } figure img { max-width: 100%; height: auto; }
figcaption { font-size: 0.88rem; color: #444; }
"""


def _numeric(text: str) -> bool:
    head = str(text).strip().split(" ")[0].lstrip("+-")
    return bool(head) and head.replace(".", "", 1).replace("e-", "", 1).replace("e+", "", 1).isdigit()


def to_html(report: Report) -> str:
    """One self-contained HTML page: inline style, figures as base64 ``data:`` URIs, nothing external."""
    esc = html.escape
    report = draw_figures(report)
    out = ["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
           f"<title>{esc(report.title)}</title>", f"<style>{_STYLE}</style>", "</head>", "<body>",
           f"<h1>{esc(report.title)}</h1>"]
    for section in report.sections:
        out.append(f"<section><h2>{esc(section.heading)}</h2>")
        for block in section.blocks:
            if isinstance(block, Paragraph):
                out.append(f"<p>{esc(block.text.strip())}</p>")
            elif isinstance(block, Preformatted):
                out.append(f"<pre>{esc(block.text.rstrip())}</pre>")
            elif isinstance(block, Figure):
                data = base64.b64encode(block.png).decode("ascii")
                out.append(f'<figure><img src="data:image/png;base64,{data}" alt="{esc(block.caption)}" '
                           f'data-figure="{esc(block.name)}"><figcaption>{esc(block.caption)}</figcaption></figure>')
            elif isinstance(block, Table):
                caption = f"<caption>{esc(block.caption)}</caption>" if block.caption else ""
                head = "".join(f"<th>{esc(c)}</th>" for c in block.columns)
                body = "".join("<tr>" + "".join(f'<td class="n">{esc(c)}</td>' if _numeric(c) else f"<td>{esc(c)}</td>"
                                                for c in row) + "</tr>" for row in block.rows)
                out.append(f'<table data-table="{esc(block.name)}">{caption}<thead><tr>{head}</tr></thead>'
                           f"<tbody>{body}</tbody></table>")
        out.append("</section>")
    out += ["</body>", "</html>", ""]
    return "\n".join(out)


def write_report(folder: str | Path, report: Report, *, member: bool = False) -> dict[str, Path]:
    """Write ``report.md``, ``report.html`` and ``figures/*.png`` into ``folder``, each atomically.

    ``member``: ``folder`` is a model folder; ``report.md`` and ``report.html`` are then recorded in
    its ``checksums.json`` like every other file of it. Returns the paths by file name.
    """
    folder = Path(folder)
    report = draw_figures(report)  # figures still pending are drawn here
    paths = {}
    for figure in report.figures():
        path = folder / FIGURES / f"{figure.name}.png"
        atomic_write_bytes(path, figure.png)
        paths[f"{FIGURES}/{figure.name}.png"] = path
    for name, text in (("report.md", to_markdown(report)), ("report.html", to_html(report))):
        if member:
            paths[name] = write_member_text(folder, name, text)
        else:
            atomic_write_text(folder / name, text)
            paths[name] = folder / name
    return paths
