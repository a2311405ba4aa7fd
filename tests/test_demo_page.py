"""The /demo page in headless Chromium against the real servers (the ``live_server`` fixture of conftest.py: a
synthetic avatar, no ARKit names; ``open_head``: the open-head demo avatar with its 52 ARKit expressions), checked as
a person sees it: frames follow the sliders, "jaw open" drives the jawOpen expression within the training range
("extremes" widens it), the filter hides rows, labels are not cut, the avatar idles (blinks, a small head motion)
until a slider is dragged and not at all for who prefers reduced motion.

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
from selenium.webdriver.common.action_chains import ActionChains
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
# Every frame message the page sends, recorded before the page's own script runs (window.__sent).
RECORD_SENT = """
window.__sent = [];
const send = WebSocket.prototype.send;
WebSocket.prototype.send = function (data) {
  try {
    const msg = JSON.parse(data);
    if (msg.frame) window.__sent.push(msg.frame);
  } catch (e) { /* not JSON: not ours */ }
  return send.call(this, data);
};
"""
SENT = "return window.__sent || [];"
VIEW_STATE = """
const img = document.getElementById('view');
return [parseInt(img.dataset.index || '0', 10), img.getAttribute('src') || ''];
"""

DECODED = """
const img = document.getElementById('view');
return img.complete && img.naturalWidth ? [img.naturalWidth, img.naturalHeight] : null;
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


def _record_sent(drv: webdriver.Chrome) -> None:
    """Record the page's frame messages (window.__sent) from the next page load on."""
    drv.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": RECORD_SENT})


def _idle_off(drv: webdriver.Chrome) -> None:
    """Untick "idle motion" (frames then come from the sliders only) and wait for the page to stop idling."""
    box = drv.find_element(By.ID, "idle")
    if box.is_selected():
        box.click()
    _wait(drv, "the idle motion to stop", lambda d: d.find_element(By.TAG_NAME, "body").get_attribute(
        "data-idle") == "off")


def _last_sent(drv: webdriver.Chrome) -> dict:
    sent = drv.execute_script(SENT)
    return sent[-1] if sent else {}


def _first_frame(drv: webdriver.Chrome) -> None:
    _wait(drv, "the first frame", lambda d: d.execute_script(FRAMES_RECEIVED) >= 1 and d.execute_script(VIEW_STATE)[1])


@pytest.fixture(scope="module")
def open_head(tmp_path_factory):
    """The service with the open-head demo avatar (52 ARKit expressions: jawOpen, eyeBlinkLeft/Right, ...), small."""
    from conftest import LiveServer

    server = LiveServer(tmp_path_factory.mktemp("open-head"), demo_avatar="open-head", demo_gaussians=2000)
    yield server
    server.stop()


def test_demo_page_streams_frames_and_follows_sliders(live_server, driver, tmp_path):
    t0 = time.perf_counter()
    _record_sent(driver)
    driver.get(f"{live_server.http_url}/demo")

    # The first frame (sent right after the header) arrives without touching anything.
    def first_frame(d):
        return d.execute_script(FRAMES_RECEIVED) >= 1 and d.execute_script(VIEW_STATE)[1]

    _wait(driver, "the first frame", first_frame)
    t_first = time.perf_counter() - t0
    _idle_off(driver)  # a new frame below is the new pose's, not the idle motion's
    index0, src0 = driver.execute_script(VIEW_STATE)
    assert index0 >= 1
    # the frame's JPEG (the client module's Frame.data) as a blob: URL, decoded at the stream's size
    assert src0.startswith("blob:"), src0
    _wait(driver, "the frame decoded", lambda d: d.execute_script(DECODED) == [512, 512])

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
    # this avatar has no jawOpen expression: "jaw open" turns the jaw joint, within its training range (0.3 rad)
    frame = _last_sent(driver)
    assert frame["joints"]["jaw"]["values"] == [0.3, 0, 0], frame
    assert "jawOpen" not in frame["namedCoefficients"], frame

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


def test_jaw_open_drives_the_jawopen_expression_within_the_training_range(open_head, driver):
    _record_sent(driver)
    driver.get(f"{open_head.http_url}/demo")
    _first_frame(driver)
    _idle_off(driver)
    jaw = driver.find_element(By.ID, "jaw")
    assert "jawOpen" in jaw.find_element(By.XPATH, "..").get_attribute("title")
    assert (jaw.get_attribute("min"), jaw.get_attribute("max")) == ("0", "0.5")  # the training range
    assert driver.find_element(By.ID, "head-yaw").get_attribute("max") == "25"
    assert driver.find_element(By.ID, "head-pitch").get_attribute("max") == "12"
    assert driver.find_element(By.ID, "camera-yaw").get_attribute("max") == "25"
    index0, src0 = driver.execute_script(VIEW_STATE)
    jaw_row = driver.find_element(By.CSS_SELECTOR, 'input[data-expression="jawOpen"]')

    driver.execute_script(SET_SLIDER, jaw, "0.4")
    _wait(driver, "a frame with jawOpen 0.4", lambda d: _last_sent(d).get("namedCoefficients", {}).get("jawOpen")
          == 0.4)
    frame = _last_sent(driver)
    assert "jaw" not in frame["joints"], frame  # the jaw joint (it tears the mouth) stays at rest
    # one coefficient: the jawOpen row shows what the jaw slider set
    assert jaw_row.get_attribute("value") == "0.4"
    assert jaw_row.find_element(By.XPATH, "../output").text == "0.40"
    _wait(driver, "the image of the open jaw", lambda d: d.execute_script(VIEW_STATE)[0] >= int(frame["index"])
          and d.execute_script(VIEW_STATE)[1] != src0)
    assert driver.execute_script(VIEW_STATE)[0] > index0

    # past the training range only with "extremes"; unticked, the value comes back into the range
    driver.execute_script(SET_SLIDER, jaw, "0.9")
    assert jaw.get_attribute("value") == "0.5"
    driver.find_element(By.ID, "extremes").click()
    assert jaw.get_attribute("max") == "1" and driver.find_element(By.ID, "camera-yaw").get_attribute("max") == "90"
    assert "extremes" in driver.find_element(By.ID, "range-note").text
    driver.execute_script(SET_SLIDER, jaw, "0.9")
    _wait(driver, "jawOpen 0.9", lambda d: _last_sent(d).get("namedCoefficients", {}).get("jawOpen") == 0.9)
    driver.find_element(By.ID, "extremes").click()
    _wait(driver, "jawOpen back to 0.5", lambda d: _last_sent(d).get("namedCoefficients", {}).get("jawOpen") == 0.5)
    assert jaw.get_attribute("value") == "0.5" and jaw_row.get_attribute("value") == "0.5"
    assert driver.execute_script("return document.body.dataset.errors") == "0"


def test_the_filter_hides_rows_and_labels_are_readable(open_head, driver, tmp_path):
    driver.get(f"{open_head.http_url}/demo")
    _first_frame(driver)
    rows = driver.find_elements(By.CSS_SELECTOR, "#expressions .row")
    assert len(rows) == 52
    # labels are whole (not cut): Left and Right are told apart; a long name wraps instead
    labels = driver.find_elements(By.CSS_SELECTOR, "#expressions .row label")
    cut = driver.execute_script("return arguments[0].filter((l) => l.scrollWidth > l.clientWidth + 1)"
                                ".map((l) => l.textContent);", labels)
    assert not cut, cut
    texts = [label.get_attribute("textContent") for label in labels]
    assert "mouthSmileLeft" in texts and "mouthSmileRight" in texts and "mouthLowerDownRight" in texts

    driver.find_element(By.ID, "filter").send_keys("smile")
    shown = [r.get_attribute("data-name") for r in rows if r.is_displayed()]
    assert shown == ["mouthsmileleft", "mouthsmileright"], shown
    hidden = driver.find_element(By.CSS_SELECTOR, '#expressions .row[data-name="jawopen"]')
    assert not hidden.is_displayed() and driver.execute_script("return arguments[0].getClientRects().length;",
                                                               hidden) == 0  # takes no room either
    screenshot = tmp_path / "demo-filtered.png"
    assert driver.save_screenshot(str(screenshot))
    if artifacts := os.environ.get("BLENDSPLAT_ARTIFACTS"):
        Path(artifacts).mkdir(parents=True, exist_ok=True)
        shutil.copy(screenshot, Path(artifacts) / screenshot.name)

    driver.find_element(By.ID, "filter").clear()
    driver.find_element(By.ID, "filter").send_keys("JAW")  # any case
    shown = [r.get_attribute("data-name") for r in rows if r.is_displayed()]
    assert shown == ["jawforward", "jawleft", "jawopen", "jawright"], shown


def test_the_avatar_idles_until_a_slider_is_dragged(open_head, driver):
    _record_sent(driver)
    driver.get(f"{open_head.http_url}/demo")
    _first_frame(driver)
    assert driver.find_element(By.ID, "idle").is_selected()
    # alive before anything is touched: frames keep coming, the head sways, the eyes blink every few seconds
    _wait(driver, "an idle blink", lambda d: any(f["namedCoefficients"].get("eyeBlinkLeft", 0) > 0.3
                                                 and f["namedCoefficients"].get("eyeBlinkRight", 0) > 0.3
                                                 for f in d.execute_script(SENT)))
    sent = driver.execute_script(SENT)
    yaws = {round(f["camera"]["orbit"]["yawDeg"], 2) for f in sent}
    assert len(sent) >= 5 and len(yaws) >= 3 and max(abs(y) for y in yaws) <= 2.5, (len(sent), sorted(yaws))
    assert driver.execute_script(FRAMES_RECEIVED) >= 5

    # dragging a slider stops the idling: what is sent is the slider's pose, nothing sways or blinks
    slider = driver.find_element(By.ID, "head-yaw")
    ActionChains(driver).click_and_hold(slider).move_by_offset(30, 0).perform()
    _wait(driver, "the idle motion to pause", lambda d: d.find_element(By.TAG_NAME, "body").get_attribute(
        "data-idle") == "off")
    time.sleep(0.5)
    during = driver.execute_script(SENT)
    time.sleep(1.0)
    after = driver.execute_script(SENT)
    assert len(after) == len(during), "idle frames were sent during the drag"
    frame = after[-1]
    assert frame["camera"]["orbit"]["yawDeg"] == 0 and "pitchDeg" not in frame["camera"]["orbit"], frame
    assert not frame["namedCoefficients"].get("eyeBlinkLeft"), frame
    ActionChains(driver).release().perform()
    _wait(driver, "the idle motion to resume", lambda d: d.find_element(By.TAG_NAME, "body").get_attribute(
        "data-idle") == "on")
    assert driver.execute_script("return document.body.dataset.errors") == "0"


def test_no_idle_motion_for_who_prefers_reduced_motion(open_head, driver):
    driver.execute_cdp_cmd("Emulation.setEmulatedMedia",
                           {"features": [{"name": "prefers-reduced-motion", "value": "reduce"}]})
    _record_sent(driver)
    driver.get(f"{open_head.http_url}/demo")
    _first_frame(driver)
    assert not driver.find_element(By.ID, "idle").is_selected()
    sent = len(driver.execute_script(SENT))
    time.sleep(1.5)
    assert len(driver.execute_script(SENT)) == sent  # nothing moves until the person moves something
