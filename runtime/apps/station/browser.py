"""A headless browser for the station: Playwright driving Debian's ``chromium`` (never
``playwright install``, which downloads a browser of its own). Used by the tests, the demo's
screenshot and the benchmarks."""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def chromium_path() -> str:
    path = CHROMIUM if Path(CHROMIUM).exists() else shutil.which("chromium")
    if path is None:
        raise FileNotFoundError("Debian's chromium is not installed: run `make deb` (apt-get install chromium)")
    return path


@contextlib.contextmanager
def headless_browser(width: int = 1400, height: int = 900):
    """A Playwright browser context (fresh profile, removed after) with a ``width`` x ``height``
    viewport; yields the context (``ctx.new_page()``)."""
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(prefix="wvr-chromium-") as profile, sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(
            profile, executable_path=chromium_path(), headless=True, args=CHROMIUM_ARGS,
            viewport={"width": width, "height": height})
        try:
            yield ctx
        finally:
            ctx.close()
