"""Headless Chromium for the viewer tests: Debian's chromium driven by playwright (its own browser download
needs a network), software WebGL; skips with the reason where either is missing or does not start."""
from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]


def chromium_path() -> str | None:
    return next((shutil.which(name) for name in ("chromium", "chromium-browser") if shutil.which(name)), None)


@contextmanager
def headless_chromium() -> Iterator[object]:
    """A playwright Browser on the machine's chromium; pytest.skip, naming why, where there is none."""
    playwright_api = pytest.importorskip("playwright.sync_api", reason="Python playwright is not installed "
                                         "(pip install '.[test]')")
    executable = chromium_path()
    if executable is None:
        pytest.skip("chromium is not installed (apt-get install chromium; .ci/run does)")
    with playwright_api.sync_playwright() as p:
        try:
            browser = p.chromium.launch(executable_path=executable, headless=True, args=ARGS)
        except Exception as error:  # noqa: BLE001 -- a browser that cannot start is the machine's, say why
            pytest.skip(f"chromium at {executable} does not start under playwright: {error}")
        try:
            yield browser
        finally:
            browser.close()
