"""The /demo page in headless Chromium against the real servers (the ``live_server`` fixture of conftest.py).

Needs Debian's chromium and chromedriver (``apt-get install -y chromium chromium-driver``); skipped without them.
Selenium is pointed at both binaries, so Selenium Manager never looks for a browser or driver on the network.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from selenium import webdriver
from selenium.common.exceptions import TimeoutException
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

WAIT_S = 60

# Dispatch 'input' the way a user's drag does (it bubbles: the page listens on the controls panel).
SET_SLIDER = """
const el = arguments[0];
el.value = arguments[1];
el.dispatchEvent(new Event('input', {bubbles: true}));
"""

FRAMES_RECEIVED = "return parseInt(document.body.dataset.framesReceived || '0', 10);"
VIEW_STATE = """
const img = document.getElementById('view');
return [parseInt(img.dataset.index || '0', 10), img.getAttribute('src') || ''];
"""


def _wait(drv: webdriver.Chrome, what: str, condition: Callable[[webdriver.Chrome], object]) -> object:
    """WebDriverWait that fails with what the page shows (status, stats, console) instead of a bare timeout."""
    try:
        return WebDriverWait(drv, WAIT_S, poll_frequency=0.05).until(condition)
    except TimeoutException:
        status = drv.find_element(By.ID, "status").text
        stats = drv.find_element(By.ID, "stats").text
        console = [f"{e['level']}: {e['message']}" for e in drv.get_log("browser")]
        pytest.fail(f"timed out after {WAIT_S} s waiting for {what}; #status={status!r}; #stats={stats!r}; "
                    f"console={console}")


def test_demo_page_streams_frames_and_follows_sliders(live_server, driver, tmp_path):
    t0 = time.perf_counter()
    driver.get(f"{live_server.http_url}/demo")

    # The first frame (sent right after the header) arrives without touching anything.
    def first_frame(d):
        return d.execute_script(FRAMES_RECEIVED) >= 1 and d.execute_script(VIEW_STATE)[1]

    _wait(driver, "the first frame", first_frame)
    t_first = time.perf_counter() - t0
    index0, src0 = driver.execute_script(VIEW_STATE)
    assert index0 >= 1
    assert src0.startswith("data:image/jpeg;base64,")

    # Controls: the avatar picker chose the fixture's avatar (or one of them), sliders were built from the header.
    assert driver.find_element(By.ID, "avatar").get_attribute("value")
    expressions = driver.find_elements(By.CSS_SELECTOR, "input[data-expression]")
    assert expressions, "no expression sliders"
    for slider_id in ("jaw", "head-yaw", "head-pitch", "camera-yaw"):
        assert driver.find_element(By.ID, slider_id).is_displayed()

    # Move the jaw and one expression: a new frame replaces the first one.
    t1 = time.perf_counter()
    driver.execute_script(SET_SLIDER, driver.find_element(By.ID, "jaw"), "0.4")
    driver.execute_script(SET_SLIDER, expressions[0], "0.8")

    def changed(d):
        index, src = d.execute_script(VIEW_STATE)
        return index > index0 and src and src != src0

    _wait(driver, "a frame of the new pose", changed)
    t_update = time.perf_counter() - t1

    screenshot = tmp_path / "demo.png"
    assert driver.save_screenshot(str(screenshot))
    assert screenshot.is_file() and screenshot.stat().st_size > 10_000, screenshot.stat().st_size
    if artifacts := os.environ.get("BLENDSPLAT_ARTIFACTS"):
        Path(artifacts).mkdir(parents=True, exist_ok=True)
        shutil.copy(screenshot, Path(artifacts) / "demo.png")

    status = driver.find_element(By.ID, "status")
    assert status.get_attribute("data-state") != "error", status.text
    assert driver.execute_script("return document.body.dataset.errors") == "0", status.text
    severe = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
    assert not severe, severe
    print(f"demo page: first frame {t_first:.2f} s after load, new pose shown {t_update:.3f} s after the change")


def test_demo_page_asks_for_a_key_once_and_streams_with_it(tmp_path, driver):
    """With keys on (the default), the page asks for a key when the server answers 401, keeps it for the browser
    session and streams over a WebSocket whose key is a subprotocol (never in the URL)."""
    from conftest import LiveServer

    server = LiveServer(tmp_path / "data", auth="keys")
    try:
        driver.get(f"{server.http_url}/demo")
        WebDriverWait(driver, WAIT_S).until(lambda d: d.switch_to.alert)
        alert = driver.switch_to.alert
        assert "API key" in alert.text
        alert.send_keys(server.api_key)
        alert.accept()
        _wait(driver, "the first frame with the key",
              lambda d: d.execute_script(FRAMES_RECEIVED) >= 1 and d.execute_script(VIEW_STATE)[1])
        assert driver.execute_script("return sessionStorage.getItem('blendsplat.apiKey')") == server.api_key
        driver.refresh()  # kept for the session: no second question
        _wait(driver, "the first frame after a reload",
              lambda d: d.execute_script(FRAMES_RECEIVED) >= 1 and d.execute_script(VIEW_STATE)[1])
    finally:
        server.stop()
