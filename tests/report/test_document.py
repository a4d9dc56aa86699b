"""One report, two renderings: Markdown with PNG files, HTML with the same PNGs inline."""

from __future__ import annotations

import base64
import json
import re

import numpy as np

from torchcal.core.workers import ready_workers, warm_up
from torchcal.report import plots
from torchcal.report.document import (
    Figure,
    Paragraph,
    PendingFigure,
    Preformatted,
    Report,
    Section,
    Table,
    draw_figures,
    to_html,
    to_markdown,
    write_report,
)


def _report() -> Report:
    png = plots.convergence([1.0, 0.1, 0.01])
    return Report("a <title>", [
        Section("first", [Paragraph("x < y & <script>alert(1)</script>"),
                          Table("numbers", ["name", "value [mm]"], [["a|b", "1.5"], ["c", "-2"]], caption="cap")]),
        Section("second", [Figure("conv", png, "the convergence"), Preformatted("  kept   as is")]),
    ])


def test_markdown_and_html_come_from_the_same_sections():
    report = _report()
    md, page = to_markdown(report), to_html(report)
    for heading in ("first", "second"):
        assert f"## {heading}" in md and f"<h2>{heading}</h2>" in page
    assert "| a\\|b | 1.5 |" in md  # a pipe in a cell does not split it
    assert "![the convergence](figures/conv.png)" in md
    assert '<table data-table="numbers">' in page and "<td>a|b</td>" in page
    assert "  kept   as is" in md and "<pre>  kept   as is</pre>" in page


def test_html_is_self_contained_and_escapes_text():
    report = _report()
    page = to_html(report)
    uris = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(uris) == 1 and base64.b64decode(uris[0]) == report.figures()[0].png
    assert report.figures()[0].png.startswith(b"\x89PNG")
    assert "<script" not in page.replace("&lt;script", "")  # the text's tag is escaped, the page has no script
    assert not re.search(r'(src|href)="(?!data:)', page)  # nothing loaded from elsewhere
    assert "<link" not in page


def test_write_report_records_model_folder_members(tmp_path):
    paths = write_report(tmp_path, _report(), member=True)
    assert (tmp_path / "figures" / "conv.png").read_bytes().startswith(b"\x89PNG")
    listed = json.loads((tmp_path / "checksums.json").read_text())["files"]
    assert {"report.md", "report.html"} <= set(listed) and paths["report.md"] == tmp_path / "report.md"
    assert not list(tmp_path.rglob("*.tmp"))  # written through temporary files, none left


def _pending_report() -> Report:
    rng = np.random.default_rng(3)
    errors = {"nominal": rng.gamma(2.0, 0.5, 200), "calibrated": rng.gamma(2.0, 0.02, 200)}
    return Report("pending", [
        Section("a", [PendingFigure("hist", plots.error_histogram, (errors, "3-D error"), "histogram"),
                      Paragraph("between")]),
        Section("b", [PendingFigure("conv", plots.convergence, ([1.0, 0.1, 0.01],), "convergence"),
                      PendingFigure("pose", plots.per_pose_errors, (np.arange(2, 202), errors, "per pose"), "per pose")]),
    ])


def test_pending_figures_are_drawn_in_place_with_their_own_bytes():
    report = _pending_report()
    drawn = draw_figures(report)
    assert [b.name for b in drawn.figures()] == ["hist", "conv", "pose"]
    assert [type(b).__name__ for b in drawn.sections[0].blocks] == ["Figure", "Paragraph"]
    assert drawn.figures()[1].png == plots.convergence([1.0, 0.1, 0.01])
    # the renderings draw what is still pending themselves
    assert to_markdown(report) == to_markdown(drawn)
    assert to_html(report) == to_html(drawn)


def test_figures_drawn_side_by_side_are_the_same_bytes():
    warm_up(2, plots.IMPORTS, wait=True)
    assert ready_workers() == 1
    serial = draw_figures(_pending_report(), jobs=1)
    parallel = draw_figures(_pending_report(), jobs=2)
    assert [f.png for f in parallel.figures()] == [f.png for f in serial.figures()]
    assert [f.name for f in parallel.figures()] == ["hist", "conv", "pose"]
