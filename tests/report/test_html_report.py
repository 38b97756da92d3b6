"""report.html: one self-contained page per report, opened from disk in a real browser.

The browser tests drive Debian's chromium through Playwright (`apt-get install chromium`,
`pip install playwright`); without either they skip, saying why. Screenshots go to
$SYNTHCAL_SCREENSHOTS when it is set (the README's pictures), else to the test's tmp folder.
"""

import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from browser import BROWSER, open_page, playwright, screenshot_dir
from stereo_bench.cli import main as stereo_bench
from stereo_bench.report.html import provenance, render_html
from stereo_bench.core.files import write_png
from quickstart import quickstart

ROOT = Path(__file__).resolve().parents[2]
@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """The quick-start rig with 12 frames, run to the end."""
    folder = tmp_path_factory.mktemp("quick")
    cfg = quickstart(12)
    rig = folder / "quick.yaml"
    rig.write_text(yaml.safe_dump(cfg))
    assert stereo_bench([str(rig), "--out", str(folder / "run")]) == 0
    return folder / "run"


def test_page_is_self_contained(tmp_path):
    figure = write_png(tmp_path / "map.png", np.full((8, 8), 128, np.uint8))
    page = render_html("t", "| method | x |\n|---|---|\n| zhang | 1 |\n", [figure],
                       provenance([3], ["abc"]), "seed: 3", methods=["zhang"])
    assert "<table>" in page and "data:image/png;base64," in page
    assert "seed: 3" in page and "abc" in page
    # Nothing to fetch: no URL of any scheme in a src or href.
    assert not re.search(r"""(src|href)\s*=\s*['"]?(https?:|//)""", page)


def test_every_report_gets_its_page(quick_run):
    page = (quick_run / "report.html").read_text()
    for method in ("zhang", "tsai", "bouguet", "opencv"):
        assert f">{method}<" in page
    assert page.count("data:image/png;base64,") == len(list((quick_run / "plots").glob("*.png")))
    assert "quickstart" in page  # the resolved rig file


@pytest.mark.skipif(BROWSER is not None, reason=BROWSER or "")
def test_report_opens_from_disk_in_chromium(quick_run, tmp_path):
    shots = screenshot_dir(tmp_path)
    with playwright.sync_playwright() as p:
        browser, page, errors = open_page(p, 1280, 900)
        requests = []
        page.on("request", lambda r: requests.append(r.url))
        page.goto((quick_run / "report.html").resolve().as_uri())
        page.wait_for_load_state("load")
        # Every figure decoded and laid out.
        sizes = page.eval_on_selector_all("figure img", "els => els.map(e => e.naturalWidth)")
        assert sizes and min(sizes) > 100
        page.screenshot(path=str(shots / "report.png"), full_page=False)
        page.evaluate("document.evaluate(\"//h2[text()='Figures']\", document, null, 9, null)"
                      ".singleNodeValue.scrollIntoView()")
        page.screenshot(path=str(shots / "report_figures.png"))
        # Pointing at a method highlights it in every table.
        page.hover("td:text-is('bouguet')")
        lit = page.eval_on_selector_all(".hl", "els => els.map(e => e.dataset.method)")
        assert lit and set(lit) == {"bouguet"}
        # A figure opens full size and zooms about the pointer.
        page.click("figure img >> nth=0")
        assert page.is_visible("#zoom")
        before = page.eval_on_selector("#zoom img", "e => e.getBoundingClientRect().width")
        page.mouse.move(640, 450)
        page.mouse.wheel(0, -600)
        after = page.eval_on_selector("#zoom img", "e => e.getBoundingClientRect().width")
        assert after > 1.5 * before
        page.screenshot(path=str(shots / "report_zoom.png"))
        page.keyboard.press("Escape")
        assert not page.is_visible("#zoom")
        browser.close()
    assert not errors, errors
    assert all(u.startswith(("file:", "data:")) for u in requests), requests
