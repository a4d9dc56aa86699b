"""report.html in a real headless browser: every image decodes, every expected table is there.

Needs Debian's ``chromium`` (``.ci/run`` installs it in CI); skipped with the reason where it is absent.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import pytest

from tests.report.test_calibration_report import FIT_TABLES

CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)

# Runs after every image has loaded or failed; writes what it found into the DOM that --dump-dom prints.
_CHECK = """<script>
window.addEventListener('load', () => {
  const images = [...document.images].map(i => ({name: i.dataset.figure, width: i.naturalWidth, height: i.naturalHeight}));
  const tables = [...document.querySelectorAll('table[data-table]')].map(t => t.dataset.table);
  const out = document.createElement('pre');
  out.id = 'torchcal-check';
  out.textContent = JSON.stringify({images, tables});
  document.body.appendChild(out);
});
</script>"""


def _render(page: str, tmp_path) -> dict:
    probe = tmp_path / "probe.html"
    probe.write_text(page.replace("</body>", _CHECK + "</body>"), encoding="utf-8")
    done = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                           "--virtual-time-budget=10000", "--dump-dom", probe.as_uri()],
                          capture_output=True, text=True, timeout=120)
    found = re.search(r'<pre id="torchcal-check">(.*?)</pre>', done.stdout, re.DOTALL)
    assert found, f"no check result in the page chromium rendered (rc {done.returncode}): {done.stderr[-1500:]}"
    return json.loads(found.group(1).replace("&quot;", '"').replace("&amp;", "&"))


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium on this machine (apt-get install chromium; .ci/run does)")
@pytest.mark.parametrize("which", ["model", "evaluation"])
def test_reports_render_with_every_image_and_table(reported, which, tmp_path):
    page = (reported[which] / "report.html").read_text(encoding="utf-8")
    result = _render(page, tmp_path)
    linked = re.findall(r"\]\(figures/([^)]+)\.png\)", (reported[which] / "report.md").read_text())
    assert len(linked) >= 6 and sorted(i["name"] for i in result["images"]) == sorted(linked)
    assert all(i["width"] > 100 and i["height"] > 100 for i in result["images"]), result["images"]
    assert set(result["tables"]) >= FIT_TABLES


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium on this machine (apt-get install chromium; .ci/run does)")
def test_a_broken_image_is_caught(tmp_path):
    """The check itself: an image that does not decode has naturalWidth 0."""
    page = ('<!DOCTYPE html><html><body><img data-figure="bad" src="data:image/png;base64,AAAA">'
            '<table data-table="t"><tr><td>1</td></tr></table></body></html>')
    result = _render(page, tmp_path)
    assert result["images"] == [{"name": "bad", "width": 0, "height": 0}] and result["tables"] == ["t"]
