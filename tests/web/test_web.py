"""The web app (`stereo-bench serve`), started as a user starts it, driven in Debian's chromium.

The server is the real command in a subprocess on a free loopback port; the browser is
Playwright's driver of /usr/bin/chromium (see tests/report/test_html_report.py for what skips without
them). Screenshots go to $SYNTHCAL_SCREENSHOTS when set.
"""


import pytest

from browser import BROWSER, open_page, playwright, screenshot_dir
from web_server import running_server

pytestmark = pytest.mark.skipif(BROWSER is not None, reason=BROWSER or "")


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """(base URL, runs folder, seconds from the command to a page that answers)."""
    runs = tmp_path_factory.mktemp("web") / "runs"
    with running_server(runs) as (url, ready):
        yield url, runs, ready


def test_compose_preview_run_and_read_the_report(server, tmp_path):
    url, runs, ready = server
    print(f"serve: {ready:.2f} s from the command to a page that answers")
    shots = screenshot_dir(tmp_path)
    with playwright.sync_playwright() as p:
        browser, page, errors = open_page(p, 1500, 1000)
        page.goto(url + "/")
        page.wait_for_function("document.querySelector('#p-image').naturalWidth > 0")
        assert page.input_value("#f-name") == "quickstart"
        # A bad value is refused with the rig file's own message, naming the field.
        page.fill("#f-frames", "0")
        page.dispatch_event("#f-frames", "change")
        page.wait_for_selector("#errors li")
        assert "trajectory.frames" in page.inner_text("#errors")
        # A small rig: 8 frames, the second camera's frame 3 previewed.
        page.fill("#f-frames", "8")
        page.dispatch_event("#f-frames", "change")
        page.wait_for_function("document.querySelector('#errors').children.length === 0")
        page.wait_for_function("document.querySelector('#p-frame').max === '7'")
        page.select_option("#p-camera", "1")
        page.fill("#p-frame", "3")
        page.dispatch_event("#p-frame", "change")
        page.wait_for_function("document.querySelector('#p-info').textContent"
                               ".includes('frame 4/8')")
        page.wait_for_function("document.querySelector('#p-trajectory').naturalWidth > 0")
        assert "frames: 8" in page.text_content("#yaml")  # the resolved rig file
        page.screenshot(path=str(shots / "web_editor.png"), full_page=True)
        page.fill("#r-name", "eight_frames")
        page.click("#b-run")
        # Live progress (a run of 8 frames may also be done before the first poll).
        page.wait_for_selector(".job.running progress, .job.done", timeout=60_000)
        page.locator("#run").screenshot(path=str(shots / "web_running.png"))
        page.wait_for_selector(".job.done", timeout=300_000)
        assert (runs / "eight_frames" / "report.html").is_file()
        assert (runs / "eight_frames" / "rig.yaml").is_file()
        with page.expect_popup() as popup:
            page.click(".job.done a.report")
        report = popup.value
        report.wait_for_load_state("load")
        sizes = report.eval_on_selector_all("figure img", "els => els.map(e => e.naturalWidth)")
        assert sizes and min(sizes) > 100
        report.screenshot(path=str(shots / "web_report.png"))
        # Past runs list it; two runs side by side.
        page.wait_for_selector("#run-list li a")
        assert "eight_frames" in page.inner_text("#run-list")
        # Save the YAML, load it back under another name, sweep it over two noise levels.
        with page.expect_download() as saved:
            page.click("#b-save")
        rig = tmp_path / "saved.yaml"
        saved.value.save_as(rig)
        assert "frames: 8" in rig.read_text()
        rig.write_text(rig.read_text().replace("name: quickstart", "name: loaded_rig", 1))
        page.set_input_files("#f-load", str(rig))
        page.wait_for_function("document.querySelector('#f-name').value === 'loaded_rig'")
        page.fill("#r-name", "two_noises")
        page.fill("#s-axes", "environment.sensor.noise_sigma: [0, 4]")
        page.click("#b-sweep")
        page.wait_for_selector("#job-2.done", timeout=300_000)
        assert (runs / "two_noises" / "sweep.html").is_file()
        assert len(list(runs.glob("two_noises/*/report.html"))) == 2
        page.goto(url + "/compare?a=eight_frames&b=eight_frames")
        frames = page.frames
        assert len(frames) == 3
        for frame in frames[1:]:
            frame.wait_for_load_state("load")
            assert "quickstart" in frame.content()
        page.screenshot(path=str(shots / "web_compare.png"))
        browser.close()
    assert not errors, errors
