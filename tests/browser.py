"""The run's page opened in a real browser: Debian's Chromium, driven by Selenium.

``make setup`` installs chromium and chromium-driver (scripts/setup.sh); Selenium is
pointed at them, so nothing downloads a browser of its own.  ``open_page`` loads a
page from file:// and returns what a person would meet: the browser's console, the
requests that failed, every image's natural size and the page's text, and saves a
screenshot.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple

import pytest

CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
#: the flags that keep Chromium off the network (this machine has none) and headless
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--window-size=1400,2400")


@dataclass
class PageVisit:
    console: List[dict]
    failed_requests: List[dict]
    requests: List[str]
    images: List[Tuple[str, int]]        # (src, naturalWidth)
    text: Dict[str, str]                 # element id -> its text
    screenshot: Path


def open_page(page: Path, screenshot: Path, ids=("verdict", "peak-flux", "steps")) -> PageVisit:
    if not (Path(CHROMIUM).exists() and Path(CHROMEDRIVER).exists()):
        pytest.fail(f"{CHROMIUM} or {CHROMEDRIVER} missing: run 'make setup' (it installs "
                    "Debian's chromium and chromium-driver)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in FLAGS:
        options.add_argument(flag)
    profile = screenshot.parent / "chromium-profile"
    options.add_argument(f"--user-data-dir={profile}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        driver.get(page.resolve().as_uri())
        # every image decoded (plots in closed <details> too), then measured
        driver.execute_async_script(
            "var done = arguments[0]; Promise.all(Array.from(document.images).map("
            "i => i.decode().catch(() => null))).then(() => done());")
        images = [tuple(x) for x in driver.execute_script(
            "return Array.from(document.images).map(i => [i.getAttribute('src'), i.naturalWidth])")]
        text = {i: driver.find_element("id", i).text for i in ids
                if driver.find_elements("id", i)}
        console = driver.get_log("browser")
        events = [json.loads(e["message"])["message"] for e in driver.get_log("performance")]
        # the page's own requests (Chromium's background lookups on a machine without a
        # network are not the page's): their URLs, and the failures among them
        uri = page.resolve().as_uri()
        sent = {e["params"]["requestId"]: e["params"]["request"]["url"] for e in events
                if e.get("method") == "Network.requestWillBeSent"
                and uri in (e["params"].get("documentURL"), e["params"]["request"]["url"])}
        failed = [dict(e["params"], url=sent[e["params"]["requestId"]]) for e in events
                  if e.get("method") == "Network.loadingFailed"
                  and e["params"]["requestId"] in sent]
        driver.save_screenshot(str(screenshot))
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)
    return PageVisit(console, failed, sorted(sent.values()), images, text, screenshot)


def check_page(page: Path, screenshot: Path) -> PageVisit:
    """The checks every recipe's page must pass; returns the visit for more."""
    visit = open_page(page, screenshot)
    assert visit.console == [], visit.console
    assert visit.failed_requests == [], visit.failed_requests
    # nothing but the page's own files: no server, no network, no CDN
    assert all(r.startswith(("file:", "data:")) for r in visit.requests), visit.requests
    assert visit.images, "the page shows no image"
    broken = [src for src, width in visit.images if not width]
    assert broken == [], broken
    srcs = [src for src, _ in visit.images]
    # relative links only: the page works wherever the directory is copied
    assert not any(s.startswith(("/", "file:", "http")) for s in srcs), srcs
    assert screenshot.stat().st_size > 10_000
    return visit


def page_numbers_equal_table(visit: PageVisit, table_json: Path) -> None:
    """Every peak and recovery of peak-flux.json stands in the page's table, to its digits."""
    table = json.loads(table_json.read_text())
    shown = visit.text["peak-flux"]
    for row in table["rows"]:
        assert row["method"] in shown
        for key in ("peak_jy", "peak_err_jy", "recovery", "recovery_err"):
            if row[key] is not None:
                assert f"{row[key]:.4f}" in shown, (row["method"], key, shown)
    pwc = next((r for r in table["rows"] if r["label"] == "pwc"), None)
    if pwc and pwc["recovery"] is not None:
        assert f"PWC recovers {pwc['recovery']:.4f}" in visit.text["verdict"]
