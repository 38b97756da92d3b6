"""Headless chromium for the browser tests, driven through Playwright: Debian's `chromium`
(`apt-get install chromium`) and `pip install playwright`; without either the tests skip, saying
why. Screenshots go to $SYNTHCAL_SCREENSHOTS when it is set (the README's pictures), else to the
test's tmp folder."""

import os
import shutil
from pathlib import Path

CHROMIUM = shutil.which("chromium")
try:
    import playwright.sync_api as playwright
except ImportError:  # pragma: no cover - depends on the machine
    playwright = None
BROWSER = (None if CHROMIUM and playwright else
           "needs Debian's chromium and the playwright package (see tests/browser.py)")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def open_page(p, width: int, height: int):
    """(browser, page, errors): chromium with a page whose console errors and uncaught
    exceptions are collected in ``errors``."""
    browser = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
    page = browser.new_page(viewport={"width": width, "height": height})
    errors = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    return browser, page, errors


def screenshot_dir(tmp_path) -> Path:
    folder = Path(os.environ.get("SYNTHCAL_SCREENSHOTS") or tmp_path)
    folder.mkdir(parents=True, exist_ok=True)
    return folder
