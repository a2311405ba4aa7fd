"""The pages' transport is the TypeScript client module (clients/js/src), shipped compiled with the server
(service/static/client/, served as /static/app/client/): /demo and /jobs import it instead of carrying their own
fetch, WebSocket and WebRTC code, and /static/app/webrtc.js is a re-export of its WebRTC session.

In headless Chromium against the real server (the ``live_server`` fixture: the synthetic demo avatar): /demo loads
the module and shows what its WebSocket stream brings, as a person sees it (a rendered head, 512 x 512, that turns
with the camera slider); a blank page of the server imports the module and streams, lists and fails the way the
node tests say (a typed NOT_FOUND naming its field). Needs Debian's chromium and chromedriver; skipped without them.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import httpx
import pytest
from selenium.common.exceptions import TimeoutException
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

STATIC = Path(__file__).resolve().parents[1] / "service" / "static"
MODULE = "/static/app/client/index.js"
WAIT_S = 60

# The shown image's size, the spread of its grey levels (a head on a background is far from flat) and a 32 x 32
# grey thumbnail (to compare two frames), or null.
IMAGE_STATS = """
const img = document.getElementById(arguments[0]);
if (!img || !img.complete || !img.naturalWidth) return null;
const c = document.createElement('canvas');
c.width = img.naturalWidth; c.height = img.naturalHeight;
const ctx = c.getContext('2d');
ctx.drawImage(img, 0, 0);
const d = ctx.getImageData(0, 0, c.width, c.height).data;
let sum = 0, sq = 0;
for (let i = 0; i < d.length; i += 4) {
  const g = (d[i] + d[i + 1] + d[i + 2]) / 3;
  sum += g; sq += g * g;
}
const n = d.length / 4;
const t = document.createElement('canvas');
t.width = t.height = 32;
t.getContext('2d').drawImage(img, 0, 0, 32, 32);
const s = t.getContext('2d').getImageData(0, 0, 32, 32).data;
const thumb = [];
for (let i = 0; i < s.length; i += 4) thumb.push((s[i] + s[i + 1] + s[i + 2]) / 3);
return {width: c.width, height: c.height, mean: sum / n, std: Math.sqrt(sq / n - (sum / n) ** 2), thumb,
        index: parseInt(img.dataset.index || '0', 10)};
"""


def _difference(a: dict, b: dict) -> float:
    """The mean absolute grey-level difference of two frames' thumbnails."""
    return sum(abs(x - y) for x, y in zip(a["thumb"], b["thumb"], strict=True)) / len(a["thumb"])


def _wait(drv, what, condition, timeout: float = WAIT_S):
    try:
        return WebDriverWait(drv, timeout, poll_frequency=0.05).until(condition)
    except TimeoutException:
        status = drv.find_elements(By.ID, "status")
        console = [f"{e['level']}: {e['message']}" for e in drv.get_log("browser")]
        pytest.fail(f"timed out after {timeout} s waiting for {what}; "
                    f"#status={status[0].text if status else None!r}; console={console}")


# ------------------------------------------------------------------------------------------- without a browser
@pytest.mark.parametrize("page", ["demo.html", "jobs.html"])
def test_the_pages_import_the_client_module_and_carry_no_transport_of_their_own(page):
    html = (STATIC / page).read_text()
    scripts = re.findall(r"<script([^>]*)>(.*?)</script>", html, flags=re.S)
    assert len(scripts) == 1 and 'type="module"' in scripts[0][0], [s[0] for s in scripts]
    code = scripts[0][1]
    assert re.search(r'^import \{[^}]+\} from "/static/app/client/index\.js";$', code, flags=re.M)
    for own in ("fetch(", "new WebSocket(", "new XMLHttpRequest(", "new EventSource(", "new RTCPeerConnection(",
                "Bearer ${"):
        assert own not in code, own
    assert not (STATIC / "webrtc.js").read_text().count("RTCPeerConnection")  # a re-export, no logic


def test_the_module_is_served_as_javascript(live_server):
    for path in (MODULE, "/static/app/client/webrtc.js", "/static/app/webrtc.js"):
        r = httpx.get(live_server.http_url + path, timeout=30)
        assert r.status_code == 200 and r.headers["content-type"].split(";")[0] == "text/javascript", (path, r)
    shipped = sorted(p.name for p in (STATIC / "client").glob("*.js"))
    sources = sorted(p.stem + ".js" for p in (STATIC.parents[1] / "clients" / "js" / "src").glob("*.ts"))
    assert shipped == sources


# ------------------------------------------------------------------------------------------- in Chromium
def test_the_demo_page_shows_the_frames_the_modules_websocket_stream_brings(live_server, driver):
    driver.get(f"{live_server.http_url}/demo")
    first = _wait(driver, "a rendered frame", lambda d: (s := d.execute_script(IMAGE_STATS, "view")) and s["index"]
                  and s)
    loaded = driver.execute_script("return performance.getEntriesByType('resource').map((e) => e.name);")
    assert f"{live_server.http_url}{MODULE}" in loaded, loaded  # the page's transport: the shipped module
    assert f"{live_server.http_url}/static/app/client/stream.js" in loaded
    # what a person sees: the stream's size, and a head on a plain background (not a flat or empty image)
    assert (first["width"], first["height"]) == (512, 512), first
    assert first["std"] > 5, first
    src = driver.find_element(By.ID, "view").get_attribute("src")
    assert src.startswith("blob:"), src  # the JPEG bytes of the module's Frame.data

    box = driver.find_element(By.ID, "idle")
    if box.is_selected():
        box.click()  # frames from the slider only
    # the last frame before the slider moves (taken before the input: the turned frame can arrive and decode
    # faster than chromedriver's next call; a new frame may be mid-decode, its blob set and the image not complete
    # yet, so wait for one that is whole)
    before = _wait(driver, "a decoded frame", lambda d: d.execute_script(IMAGE_STATS, "view"))
    assert before["index"] >= first["index"]
    driver.execute_script("const el = document.getElementById('camera-yaw'); el.value = el.max;"
                          "el.dispatchEvent(new Event('input', {bubbles: true}));")
    turned = _wait(driver, "the head turned by the camera slider", lambda d: (
        (s := d.execute_script(IMAGE_STATS, "view")) and s["index"] > before["index"]
        and _difference(s, first) > 4 and s))
    assert turned["std"] > 5
    print(f"the camera slider changed the picture by {_difference(turned, first):.1f} grey levels on average")
    stats = driver.find_element(By.ID, "stats").text
    assert re.search(r"frames \d+ · server [\d.]+ ms · round trip \d+ ms · dropped \d+", stats), stats
    assert driver.execute_script("return document.body.dataset.errors") == "0"
    severe = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
    assert not severe, severe


IMPORT_AND_STREAM = """
const done = arguments[arguments.length - 1];
(async () => {
  const { Client, BlendsplatError } = await import('/static/app/client/index.js');
  const { connectWebRTC, parseIceServers } = await import('/static/app/webrtc.js');
  const client = new Client();  // this page's origin
  const avatars = await client.listAvatars();
  let refused = null;
  try { await client.getAvatar('no-such-avatar'); } catch (e) {
    refused = {typed: e instanceof BlendsplatError, code: e.code, field: e.field, http: e.httpStatus};
  }
  const stream = await client.stream('demo', {size: 96, codec: 'jpeg'});
  stream.send({expression: {}, camera: {yaw: 0}});
  const frame = await stream.receive();
  await stream.finish();
  const img = document.createElement('img');
  img.id = 'shown';
  img.src = URL.createObjectURL(new Blob([frame.data], {type: 'image/jpeg'}));
  await img.decode();
  document.body.append(img);
  done({avatars: avatars.map((a) => a.id), refused, header: stream.header.width, index: frame.index,
        final: stream.final, webrtc: typeof connectWebRTC,
        ice: parseIceServers('<turn:t.example:3478>; rel="ice-server"; username="u"; credential="c"')});
})().catch((e) => done({error: String(e && e.stack || e)}));
"""


def test_a_page_of_the_server_imports_the_module_and_streams_with_it(live_server, driver):
    driver.get(f"{live_server.http_url}/healthz")  # any page of the server: the module is same-origin
    driver.set_script_timeout(WAIT_S)
    got = driver.execute_async_script(IMPORT_AND_STREAM)
    assert "error" not in got, got.get("error")
    assert "demo" in got["avatars"]
    assert got["refused"] == {"typed": True, "code": "NOT_FOUND", "field": "avatar_id", "http": 404}
    assert got["header"] == 96 and got["index"] == 1
    assert got["final"]["code"] == "OK" and got["final"]["framesSent"] == 1
    assert got["webrtc"] == "function"
    assert got["ice"] == [{"urls": "turn:t.example:3478", "username": "u", "credential": "c"}]
    shown = driver.execute_script(IMAGE_STATS, "shown")
    assert (shown["width"], shown["height"]) == (96, 96) and shown["std"] > 5, shown


# ------------------------------------------------------------------------------------------- WebRTC through TURN
RELAY_BY_LINK = """
const done = arguments[arguments.length - 1];
(async () => {
  const { connectWebRTC } = await import('/static/app/client/index.js');
  const video = document.createElement('video');
  document.body.append(video);
  const session = await connectWebRTC({avatar: 'demo', size: 64, video, iceTransportPolicy: 'relay'});
  await Promise.race([session.ready, new Promise((_, no) => setTimeout(() => no(new Error('no header')), 20000))]);
  for (let i = 0; i < 150 && session.stats.frames < 5; i++) {
    session.sendPose({camera: {yaw: i % 10}});
    await new Promise((ok) => setTimeout(ok, 50));
  }
  const stats = await session.pc.getStats();
  const types = {};
  stats.forEach((r) => { if (r.type === 'local-candidate') types[r.id] = r.candidateType; });
  let local = null;
  stats.forEach((r) => {
    if (r.type !== 'transport' || !r.selectedCandidatePairId) return;
    local = types[stats.get(r.selectedCandidatePairId).localCandidateId];
  });
  const result = {iceServers: session.iceServers, frames: session.stats.frames, local, locals: Object.values(types)};
  await session.close();
  done(result);
})().catch((e) => done({error: String(e && e.stack || e)}));
"""


@pytest.mark.slow
def test_webrtc_without_ice_servers_relays_through_the_turn_server_of_the_link_headers(tmp_path, coturn):
    """The caller passes no iceServers and allows relay candidates only: the module reads the TURN server (and its
    short-lived credentials) from the 201's WHEP Link headers and offers again through it; frames arrive over it."""
    from conftest import LiveServer, chromium

    turn_url, secret = coturn  # the conftest's coturn on 127.0.0.1
    s = LiveServer(tmp_path / "data", webrtc_host_addresses=["127.0.0.1"], webrtc_turn_urls=[turn_url],
                   webrtc_turn_secret=secret)
    browser = chromium(tmp_path / "profile", "--allow-loopback-in-peer-connection",
                       "--disable-features=WebRtcHideLocalIpsWithMdns", "--autoplay-policy=no-user-gesture-required")
    try:
        drv = next(browser)
        drv.get(f"{s.http_url}/healthz")  # a page of the server: the module's fetches are same-origin
        drv.set_script_timeout(90)
        got = drv.execute_async_script(RELAY_BY_LINK)
        assert "error" not in got, (got["error"], (tmp_path / "turnserver.log").read_text()[-1500:])
        [server] = got["iceServers"]
        assert server["urls"] == turn_url and server["username"].endswith(":blendsplat") and server["credential"]
        assert got["frames"] >= 5 and got["local"] == "relay" and set(got["locals"]) == {"relay"}, got
        metrics = s.engine.metrics
        deadline = time.monotonic() + 5
        while metrics.webrtc_sessions._value.get() and time.monotonic() < deadline:  # the first offer's too
            time.sleep(0.05)
        assert metrics.webrtc_sessions._value.get() == 0
    finally:
        browser.close()
        s.stop()
