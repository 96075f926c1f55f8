"""A real headless Chromium (the distribution's ``chromium`` and ``chromium-driver``)
driven by Selenium, for the tests of ``uma view``'s page.

The machine's network is closed: Chromium starts with everything that would call home
switched off and a fresh profile.  When something it needs cannot exist here the test is
skipped with the reason, except where ``UMA_REQUIRE_BROWSER`` is set (``.ci/run`` sets it
after installing Chromium): there a missing browser fails the test.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from typing import Any

import pytest

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         # WebGL in software (SwiftShader): the page's 3D scene needs it without a GPU
         "--enable-unsafe-swiftshader", "--window-size=1280,900")

#: Run before every page's own scripts: ``requestAnimationFrame`` callbacks come at most five
#: times a second.  A live scene is redrawn at every animation frame, and in software WebGL
#: that is most of a browser test's CPU without this (about 0.85 CPU-s per second on a
#: loaded 2-core host, 0.2 at five frames); the page's text, which the tests read, does
#: not wait on frames.
FIVE_FPS = """(() => {
  const raf = window.requestAnimationFrame.bind(window);
  const caf = window.cancelAnimationFrame.bind(window);
  const pending = new Map();  // our id -> -timeout id (waiting) or the browser's frame id
  let next = 1;
  window.requestAnimationFrame = (cb) => {
    const id = next++;
    pending.set(id, -setTimeout(() => {
      pending.set(id, raf((t) => { pending.delete(id); cb(t); }));
    }, 200));
    return id;
  };
  window.cancelAnimationFrame = (id) => {
    const handle = pending.get(id);
    if (handle === undefined) return;
    pending.delete(id);
    if (handle < 0) clearTimeout(-handle); else caf(handle);
  };
})();"""


def unavailable() -> str | None:
    """Why no browser test can run here, or None."""
    for path in (CHROMIUM, CHROMEDRIVER):
        if not os.access(path, os.X_OK):
            return f"{path} is missing (apt-get install -y chromium chromium-driver)"
    try:
        import selenium  # noqa: F401
        import viser  # noqa: F401
    except ImportError as exc:
        return f"{exc.name} is not installed (pip install -e '.[dev]')"
    return None


@contextlib.contextmanager
def chromium() -> Iterator[Any]:
    """A headless Chromium under Selenium for a test, skipped (module docstring) when it
    cannot exist here."""
    reason = unavailable()
    if reason:
        if os.environ.get("UMA_REQUIRE_BROWSER"):
            pytest.fail(f"UMA_REQUIRE_BROWSER is set but {reason}")
        pytest.skip(reason)
    with chromium_driver() as driver:
        yield driver


@contextlib.contextmanager
def chromium_driver() -> Iterator[Any]:
    """A headless Chromium under Selenium, quit (and its profile removed) at the end."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="uma-chromium-")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in (*FLAGS, f"--user-data-dir={profile}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": FIVE_FPS})
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def page_text(driver: Any) -> str:
    from selenium.webdriver.common.by import By

    return driver.find_element(By.TAG_NAME, "body").text


def wait_text(driver: Any, pred: Any, timeout: float, what: str) -> str:
    """The page's text once ``pred(text)`` holds; bounded in time."""
    deadline = time.monotonic() + timeout
    text = ""
    while time.monotonic() < deadline:
        text = page_text(driver)
        if pred(text):
            return text
        time.sleep(0.1)
    raise AssertionError(f"the page never showed {what} within {timeout} s; it shows:\n{text}")


def scene_png(driver: Any) -> bytes:
    """A screenshot of the 3D scene (the page's largest canvas)."""
    from selenium.webdriver.common.by import By

    canvases = driver.find_elements(By.TAG_NAME, "canvas")
    assert canvases, "the page has no canvas"
    big = max(canvases, key=lambda c: c.size["width"] * c.size["height"])
    return big.screenshot_as_png
