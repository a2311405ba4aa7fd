"""The /jobs page (service/static/jobs.html) in headless Chromium.

- Against a real `blendsplat up` (the service and its training worker child) on free loopback ports and a tmp data
  dir: a non-archive upload shows the server's 422 reason; a tracked-video archive is uploaded through the page's
  file input (the avatar id defaults from the file name), a tiny-preset job started from the page shows live progress
  and is cancelled with the page's Cancel button; a second short job succeeds, its curves and preview show, "Open in
  demo" opens the trained avatar in /demo; a job is deleted from the page (with its confirm). The page follows the
  job by server-sent events where the server has ``/v1/jobs/{id}/events`` and by polling where it has not yet.
- Against a small scripted HTTP server that speaks the events contract (``id:`` / ``event:`` / ``data:``) and serves
  the page with the client module it imports (service/static/client/): the module's SSE reader (fetch +
  ReadableStream, the API key sent as a Bearer header, which EventSource cannot do)
  parses events in odd pieces and CRLF lines, resumes with ``Last-Event-ID`` after a dropped connection, shows the
  preview beside its ground truth, and keeps the key for the browser session.

Needs Debian's chromium and chromedriver (``apt-get install -y chromium chromium-driver``); skipped without them.
Screenshots (during training, and finished) are written to the test's tmp dir and copied to /tmp/jobs-page-*.png
(and to $BLENDSPLAT_ARTIFACTS when set).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import struct
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from selenium import webdriver
from selenium.common.exceptions import TimeoutException
from selenium.webdriver.common.by import By
from selenium.webdriver.support import expected_conditions
from selenium.webdriver.support.ui import WebDriverWait
from test_jobs_api import ServerProcess

PAGE = Path(__file__).resolve().parents[1] / "service" / "static" / "jobs.html"
WAIT_S = 60
SCREENSHOTS = {"training": Path("/tmp/jobs-page-training.png"), "finished": Path("/tmp/jobs-page-finished.png")}
# Resource errors the page causes on purpose: the refused upload (422) and, on a server without the events route
# yet, its probe of /v1/jobs/{id}/events (404) before it polls.
EXPECTED_CONSOLE = (re.compile(r"/v1/uploads - Failed to load resource: .* 422"),
                    re.compile(r"/v1/jobs/[^ ]+/events - Failed to load resource: .* 404"))


def _text(drv: webdriver.Chrome, element_id: str) -> str:
    found = drv.find_elements(By.ID, element_id)  # textContent: .text is what CSS shows (the badges' uppercase)
    return " ".join((found[0].get_attribute("textContent") or "").split()) if found else "<none>"


def _wait(drv: webdriver.Chrome, what: str, condition: Callable[[webdriver.Chrome], object],
          timeout: float = WAIT_S, log: Callable[[], str] | None = None) -> object:
    """WebDriverWait that fails with what the page shows (status, live mode, progress, errors, console) and the
    server's log tail instead of a bare timeout."""
    try:
        return WebDriverWait(drv, timeout, poll_frequency=0.05).until(condition)
    except TimeoutException:
        shown = {i: _text(drv, i) for i in ("status", "live-mode", "job-state", "progress-text", "upload-text",
                                            "upload-error", "job-form-error", "jobs-error", "job-error")}
        console = [f"{e['level']}: {e['message']}" for e in drv.get_log("browser")]
        pytest.fail(f"timed out after {timeout} s waiting for {what}; page: {shown}; console: {console}"
                    + (f"\nserver log:\n{log()[-3000:]}" if log else ""))


def _iteration(drv: webdriver.Chrome) -> int:
    match = re.search(r"iteration ([\d,]+)", _text(drv, "progress-text"))
    return int(match.group(1).replace(",", "")) if match else 0


def _chart_points(drv: webdriver.Chrome, chart: str = "chart-loss") -> int:
    match = re.search(r"(\d+) points", drv.find_element(By.ID, chart).get_attribute("aria-label") or "")
    return int(match.group(1)) if match else 0


def _screenshot(drv: webdriver.Chrome, tmp_path: Path, name: str) -> Path:
    shot = tmp_path / f"jobs-page-{name}.png"
    assert drv.save_screenshot(str(shot))
    assert shot.stat().st_size > 10_000, shot.stat().st_size
    shutil.copy(shot, SCREENSHOTS[name])
    if artifacts := os.environ.get("BLENDSPLAT_ARTIFACTS"):
        Path(artifacts).mkdir(parents=True, exist_ok=True)
        shutil.copy(shot, Path(artifacts) / shot.name)
    return shot


def _unexpected_console(drv: webdriver.Chrome) -> list[str]:
    return [e["message"] for e in drv.get_log("browser")
            if e["level"] == "SEVERE" and not any(p.search(e["message"]) for p in EXPECTED_CONSOLE)]


def _fill(drv: webdriver.Chrome, element_id: str, value: str) -> None:
    field = drv.find_element(By.ID, element_id)
    field.clear()
    field.send_keys(value)


# --------------------------------------------------------------------------------------------- real server
def test_upload_train_watch_cancel_and_open_a_trained_avatar(driver, tmp_path, tiny_video_archive):
    t0 = time.perf_counter()
    archive = tmp_path / "Ada's take 1.tar.gz"  # the avatar id defaults to a sanitised "Ada-s-take-1"
    archive.write_bytes(tiny_video_archive)
    not_an_archive = tmp_path / "notes.txt"
    not_an_archive.write_text("tracked video? no, a shopping list\n" * 20)
    # progress every 0.5 s (the heartbeat carries it); the default upload limit of the test servers is 1 MiB
    up = ServerProcess(tmp_path / "data", command="up", BLENDSPLAT_HEARTBEAT_SECONDS="0.5",
                       BLENDSPLAT_MAX_DATASET_BYTES=str(64 << 20))
    log = up.output
    try:
        t_up = time.perf_counter() - t0
        # keys are on (the default): the server created its admin key at first start; the page keeps the key it
        # is given for the browser session (sessionStorage, as the page's "Use" button stores it: the key test
        # below clicks it), so it is put there first and the page never answers a 401
        # without a key the list says it could not be loaded (not "loading…" for ever) and why
        driver.get(f"{up.url}/jobs")
        _wait(driver, "the list's failure", lambda d: "not loaded" in _text(d, "jobs"), log=log)
        assert "API key is required" in driver.find_element(By.ID, "jobs-error").text
        driver.get_log("browser")  # read (and so cleared): that 401 was the point
        driver.get(f"{up.url}/healthz")
        driver.execute_script("sessionStorage.setItem('blendsplat.apiKey', arguments[0])",
                              (tmp_path / "data" / "admin.key").read_text().strip())
        driver.get(f"{up.url}/jobs")
        _wait(driver, "the empty job list", lambda d: "no jobs yet" in _text(d, "jobs"), log=log)
        assert driver.find_element(By.ID, "start").get_attribute("disabled") is not None  # nothing uploaded yet

        # a file that is no archive: the server's 422 reason is shown, nothing can be started
        driver.find_element(By.ID, "file").send_keys(str(not_an_archive))
        _wait(driver, "the upload refusal", lambda d: d.find_element(By.TAG_NAME, "body").get_attribute(
            "data-upload") == "refused", log=log)
        refusal = _text(driver, "upload-error")
        assert "notes.txt was not accepted" in refusal and "not a .tar, .tar.gz or .zip archive" in refusal, refusal
        assert "error" in _text(driver, "status")
        assert driver.find_element(By.ID, "start").get_attribute("disabled") is not None

        # the archive: uploaded with a progress bar, then described
        driver.find_element(By.ID, "file").send_keys(str(archive))
        _wait(driver, "the upload", lambda d: d.find_element(By.TAG_NAME, "body").get_attribute(
            "data-upload") == "done", log=log)
        assert "12 frames, 64×64" in _text(driver, "upload-text"), _text(driver, "upload-text")
        assert _text(driver, "upload-error") == ""
        assert driver.find_element(By.ID, "avatar-id").get_attribute("value") == "Ada-s-take-1"
        assert driver.find_element(By.ID, "preset").get_attribute("value") == "tiny"

        # a long job: started, watched until the page shows progress, cancelled from the page
        _fill(driver, "iterations", "2000")
        t_submit = time.perf_counter()
        driver.find_element(By.ID, "start").click()
        _wait(driver, "the job view", lambda d: d.find_element(By.ID, "job-view").is_displayed(), log=log)
        first_id = _text(driver, "job-id")
        assert first_id.startswith("job_"), first_id
        _wait(driver, "a progress update on the page", lambda d: _iteration(d) > 0, log=log)
        t_progress = time.perf_counter() - t_submit
        assert _text(driver, "job-state") == "running"
        assert "/ 2,000" in _text(driver, "progress-text"), _text(driver, "progress-text")
        live = driver.find_element(By.TAG_NAME, "body").get_attribute("data-live")
        assert live in ("events", "polling"), live
        _wait(driver, "a few points on the curves and an ETA", lambda d: _chart_points(d) >= 3
              and "ETA" in _text(d, "progress-text"), timeout=30, log=log)
        assert _text(driver, "stat-gaussians") not in ("", "–") and _text(driver, "stat-psnr").endswith("dB")
        _screenshot(driver, tmp_path, "training")

        driver.find_element(By.ID, "cancel").click()
        _wait(driver, "the state cancelled", lambda d: _text(d, "job-state") == "cancelled", log=log)
        cancelled_at = _iteration(driver)
        assert 0 < cancelled_at < 2000
        assert driver.find_element(By.ID, "cancel").get_attribute("disabled") is not None
        assert not driver.find_element(By.ID, "open-demo").is_displayed()
        # the download buttons stay disabled, and say why (their tooltip)
        contact = driver.find_element(By.ID, "download-contact")
        assert contact.get_attribute("disabled") is not None
        assert "cancelled before training ended" in contact.get_attribute("title"), contact.get_attribute("title")
        _wait(driver, "the list to show it cancelled", lambda d: "cancelled" in d.find_element(
            By.CSS_SELECTOR, f'#jobs button[data-id="{first_id}"] .badge').get_attribute("textContent"), log=log)

        # a short job that succeeds: result, curves, preview, report, "Open in demo"
        _fill(driver, "avatar-id", "ada")
        _fill(driver, "iterations", "30")
        driver.find_element(By.ID, "start").click()
        _wait(driver, "the second job", lambda d: _text(d, "job-id") not in ("", first_id), log=log)
        second_id = _text(driver, "job-id")
        _wait(driver, "the state succeeded", lambda d: _text(d, "job-state") == "succeeded", timeout=120, log=log)
        _wait(driver, "the result and links", lambda d: d.find_element(By.ID, "open-demo").is_displayed()
              and d.find_element(By.ID, "download-report").get_attribute("disabled") is None, log=log)
        _wait(driver, "the preview image", lambda d: d.find_element(By.ID, "preview-img").is_displayed()
              and d.execute_script("const i = document.getElementById('preview-img');"
                                   "return i.complete && i.naturalWidth > 0;"), log=log)
        assert "ada is in the store" in _text(driver, "result"), _text(driver, "result")
        # the main install draws the figures (matplotlib): the contact sheet can be downloaded, nothing is missing
        contact = driver.find_element(By.ID, "download-contact")
        assert contact.is_displayed() and contact.is_enabled(), contact.get_attribute("title")
        assert not driver.find_element(By.ID, "artefact-note").is_displayed(), _text(driver, "artefact-note")
        assert _text(driver, "progress-text").startswith("iteration 30 / 30 · 100.0 %")
        assert _chart_points(driver) >= 1 and _chart_points(driver, "chart-psnr") >= 1
        truth_shown = driver.find_element(By.ID, "truth-fig").is_displayed()
        demo_link = driver.find_element(By.ID, "open-demo")
        assert demo_link.get_attribute("href") == f"{up.url}/demo?avatar=ada"
        assert driver.find_element(By.CSS_SELECTOR, f'#jobs button[data-id="{second_id}"]').get_attribute(
            "aria-current") == "true"
        _screenshot(driver, tmp_path, "finished")

        # delete the cancelled job from the page (after its confirm)
        driver.find_element(By.CSS_SELECTOR, f'#jobs button[data-id="{first_id}"]').click()
        _wait(driver, "the first job's view", lambda d: _text(d, "job-id") == first_id
              and _text(d, "job-state") == "cancelled", log=log)
        driver.find_element(By.ID, "delete").click()
        WebDriverWait(driver, 10).until(expected_conditions.alert_is_present())
        alert = driver.switch_to.alert
        assert first_id in alert.text
        alert.accept()
        _wait(driver, "the deleted job to leave the list", lambda d: not d.find_elements(
            By.CSS_SELECTOR, f'#jobs button[data-id="{first_id}"]'), log=log)
        assert up.http.get(f"/v1/jobs/{first_id}").status_code == 404
        assert not (tmp_path / "data" / "work" / first_id).exists()

        unexpected = _unexpected_console(driver)
        assert not unexpected, unexpected

        # one click to the trained avatar in /demo
        driver.find_element(By.CSS_SELECTOR, f'#jobs button[data-id="{second_id}"]').click()
        _wait(driver, "the link to the demo", lambda d: d.find_element(By.ID, "open-demo").is_displayed(), log=log)
        driver.find_element(By.ID, "open-demo").click()
        _wait(driver, "the trained avatar streaming in /demo", lambda d: d.current_url.endswith("/demo?avatar=ada")
              and d.find_element(By.ID, "avatar").get_attribute("value") == "ada"
              and int(d.execute_script("return document.body.dataset.framesReceived || '0'")) >= 1, log=log)
    finally:
        code = up.stop()
    assert code == 0
    print(f"jobs page: up ready {t_up:.1f} s; first progress on the page {t_progress:.1f} s after Start "
          f"(followed by {live}); cancelled at iteration {cancelled_at}; ground truth shown: {truth_shown}; "
          f"total {time.perf_counter() - t0:.1f} s")


# ------------------------------------------------------------------------------------ scripted events server
def _png(width: int = 8, height: int = 8, rgb: tuple[int, int, int] = (200, 120, 60)) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    rows = b"".join(b"\0" + bytes(rgb) * width for _ in range(height))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


class ScriptedJobs:
    """One job and its events, served as service/jobs/api.py serves them; the events stream is scripted:
    connection 1 sends events 1-3 in odd pieces and drops; connection 2 (which must resume after 3) sends 4-6 with
    CRLF line ends, waits for the page's cancel, sends the terminal state event 7 and closes; later connections
    replay what comes after their Last-Event-ID, then close (as for a finished job). A second job's events answer
    404 as a server without the events route does."""

    JOB = "job_scripted0000000000000001"
    NO_EVENTS = "job_scripted0000000000000002"
    NO_SHEET = "job_scripted0000000000000003"  # succeeded; its worker could not draw the contact sheet
    NO_SHEET_REASON = (f"job {NO_SHEET} has no contact-sheet: the worker could not draw it (matplotlib is not "
                       "installed: pip install 'blendsplat[train]')")

    def __init__(self):
        self.lock = threading.Lock()
        self.requests: list[tuple[str, str, str | None, str | None]] = []  # method, path, Authorization, Last-Event-ID
        self.cancelled = threading.Event()
        self.connections = 0
        self.state, self.preview = "running", False
        progress = [{"iteration": i, "total_iterations": 100, "fraction": i / 100, "eta_seconds": 100 - i,
                     "loss": 0.5 / i, "psnr": 10 + i / 5, "gaussians": 20_000 + i} for i in (10, 20, 30)]
        self.events = [("state", {"state": "running", "previous": "queued", "attempts": 1}),
                       ("progress", progress[0]), ("progress", progress[1]), ("progress", progress[2]),
                       ("preview", {"iteration": 30, "path": "preview.png",
                                    "url": f"/v1/jobs/{self.JOB}/artefacts/preview"}),
                       ("log", {"message": "cancel requested"}),
                       ("state", {"state": "cancelled", "previous": "running", "attempts": 1})]

    def frame(self, n: int, crlf: bool = False) -> bytes:
        kind, data = self.events[n - 1]
        end = "\r\n" if crlf else "\n"
        return f"id: {n}{end}event: {kind}{end}data: {json.dumps(data)}{end}{end}".encode()

    def job(self) -> dict:
        last = self.events[3][1] if self.preview else self.events[2][1]
        artefacts = {name: f"/v1/jobs/{self.JOB}/artefacts/{name}" for name in ("preview", "truth", "log")
                     if self.preview or name == "log"}
        return {"id": self.JOB, "state": self.state, "attempts": 1, "max_attempts": 3,
                "cancel_requested": self.cancelled.is_set(), "progress": last, "error": None, "result": None,
                "spec": {"upload_id": "upl_scripted0000000001", "preset": "tiny", "iterations": 100,
                         "avatar_id": "scripted", "resolution": None, "seed": 0},
                "created_at": "2026-01-01T00:00:00Z", "started_at": "2026-01-01T00:00:01Z",
                "finished_at": None, "updated_at": "2026-01-01T00:00:02Z",
                "links": {"self": f"/v1/jobs/{self.JOB}", "cancel": f"/v1/jobs/{self.JOB}/cancel",
                          "upload": None, "artefacts": artefacts, "avatar": None}}

    def handler(self) -> type[BaseHTTPRequestHandler]:
        script = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:  # quiet
                pass

            def _note(self) -> None:
                if self.path.startswith("/static/"):  # the page's own files: not API requests
                    return
                with script.lock:
                    script.requests.append((self.command, self.path, self.headers.get("Authorization"),
                                            self.headers.get("Last-Event-ID")))

            def _send(self, status: int, body: bytes, media_type: str) -> None:
                self.send_response(status)
                self.send_header("Content-Type", media_type)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def _json(self, status: int, body: dict) -> None:
                self._send(status, json.dumps(body).encode(), "application/json")

            def do_GET(self) -> None:  # noqa: N802 - http.server's name
                self._note()
                path = self.path.split("?")[0]
                base = f"/v1/jobs/{script.JOB}"
                if path == "/jobs":
                    self._send(200, PAGE.read_bytes(), "text/html")
                elif path == "/static/app/theme.css":  # the pages' shared stylesheet, as the app serves it
                    self._send(200, (PAGE.parent / "theme.css").read_bytes(), "text/css")
                elif re.fullmatch(r"/static/app/client/[a-z]+\.js", path):  # the client module the page imports
                    self._send(200, (PAGE.parent / "client" / path.rsplit("/", 1)[1]).read_bytes(), "text/javascript")
                elif path == "/v1/jobs":
                    self._json(200, {"jobs": [script.job()], "next_cursor": None})
                elif path == base:
                    self._json(200, script.job())
                elif path == f"/v1/jobs/{script.NO_EVENTS}":
                    job = script.job() | {"id": script.NO_EVENTS, "state": "running", "cancel_requested": False}
                    job["progress"] = script.events[1][1] | {"iteration": 5}
                    job["links"] = job["links"] | {"artefacts": {}}
                    self._json(200, job)
                elif path == f"/v1/jobs/{script.NO_SHEET}":
                    job = script.job() | {"id": script.NO_SHEET, "state": "succeeded", "cancel_requested": False,
                                          "result": {"avatar_id": "scripted", "iterations": 100}}
                    job["links"] = job["links"] | {"artefacts": {
                        name: f"/v1/jobs/{script.NO_SHEET}/artefacts/{name}" for name in ("report", "log")}}
                    self._json(200, job)
                elif path == f"/v1/jobs/{script.NO_SHEET}/artefacts/contact-sheet":
                    self._json(404, {"error": {"code": "NOT_FOUND", "message": script.NO_SHEET_REASON,
                                               "field": "name"}})
                elif path in (f"{base}/artefacts/preview", f"{base}/artefacts/truth") and script.preview:
                    self._send(200, _png(rgb=(200, 120, 60) if path.endswith("preview") else (60, 120, 200)),
                               "image/png")
                elif path == f"{base}/events":
                    self._events()
                else:
                    self._json(404, {"error": {"code": "NOT_FOUND", "message": f"no {path}", "field": ""}})

            def do_POST(self) -> None:  # noqa: N802
                self._note()
                if self.path == f"/v1/jobs/{script.JOB}/cancel":
                    script.cancelled.set()
                    self._json(202, script.job())
                else:
                    self._json(404, {"error": {"code": "NOT_FOUND", "message": "no such route", "field": ""}})

            def _write(self, data: bytes) -> None:
                self.wfile.write(data)
                self.wfile.flush()

            def _events(self) -> None:
                with script.lock:
                    script.connections += 1
                    connection = script.connections
                after = int(self.headers.get("Last-Event-ID") or 0)
                self.send_response(200)
                self.send_header("Content-Type", "text/event-stream; charset=utf-8")
                self.send_header("Cache-Control", "no-store")
                self.end_headers()  # HTTP/1.0: the body ends when the connection closes
                if connection == 1:
                    body = b"retry: 300\n: a comment line\n\n" + b"".join(script.frame(n) for n in (1, 2, 3))
                    for start in range(0, len(body), 37):  # pieces that split lines and fields
                        self._write(body[start:start + 37])
                        time.sleep(0.01)
                    time.sleep(0.8)
                    return  # dropped without the terminal state event
                if connection == 2:
                    script.preview = True
                    for n in range(after + 1, 7):
                        self._write(script.frame(n, crlf=True))
                    if script.cancelled.wait(30):
                        script.state = "cancelled"
                        self._write(script.frame(7))
                    return
                for n in range(after + 1, len(script.events) + 1):
                    self._write(script.frame(n))

        return Handler


@pytest.fixture
def scripted() -> Iterator[tuple[ScriptedJobs, str]]:
    script = ScriptedJobs()
    server = ThreadingHTTPServer(("127.0.0.1", 0), script.handler())
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield script, f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        script.cancelled.set()
        server.shutdown()
        server.server_close()


def test_events_are_read_with_the_key_and_resumed_after_a_dropped_connection(driver, scripted):
    script, url = scripted
    driver.get(f"{url}/jobs")
    _wait(driver, "the job list", lambda d: d.find_elements(By.CSS_SELECTOR, f'#jobs button[data-id="{script.JOB}"]'))

    # the key, asked once: sent as a Bearer header from now on and kept for the browser session
    _fill(driver, "api-key", "key-for-this-session")
    driver.find_element(By.ID, "key-save").click()
    _wait(driver, "the key to be used", lambda d: "key set" in _text(d, "key-state"))
    driver.find_element(By.CSS_SELECTOR, f'#jobs button[data-id="{script.JOB}"]').click()

    # connection 1 (events 1-3 in pieces, then dropped), connection 2 resumes after event 3
    _wait(driver, "event 4 after the resume", lambda d: _iteration(d) == 30)
    assert driver.find_element(By.TAG_NAME, "body").get_attribute("data-live") in ("events", "reconnecting")
    _wait(driver, "the preview beside its ground truth", lambda d: d.find_element(By.ID, "truth-fig").is_displayed()
          and d.execute_script("return ['preview-img', 'truth-img'].every((id) => {"
                               "const i = document.getElementById(id); return i.complete && i.naturalWidth === 8; });"))
    assert _chart_points(driver) == 3 and _chart_points(driver, "chart-psnr") == 3
    assert "ETA 1 min 10 s" in _text(driver, "progress-text") and _text(driver, "stat-gaussians") == "20,030"
    assert "cancel requested" in _text(driver, "events-log")
    assert "resuming after event 3" in _text(driver, "events-log")

    driver.find_element(By.ID, "cancel").click()
    _wait(driver, "the terminal state event", lambda d: _text(d, "job-state") == "cancelled"
          and d.find_element(By.TAG_NAME, "body").get_attribute("data-live") == "ended")
    events = [r for r in script.requests if r[1].endswith("/events")]
    assert [r[3] for r in events] == [None, "3"], events
    first_keyed = next(i for i, r in enumerate(script.requests) if r[2])
    keyed = script.requests[first_keyed:]  # every request once the key was given, the events' included
    assert all(auth == "Bearer key-for-this-session" for _, _, auth, _ in keyed), keyed
    assert all(r in keyed for r in events)
    assert ("POST", f"/v1/jobs/{script.JOB}/cancel", "Bearer key-for-this-session", None) in script.requests

    # a reload keeps the key and the selected job; a finished job's events are replayed once, then the stream ends
    driver.refresh()
    _wait(driver, "the replayed job", lambda d: _text(d, "job-state") == "cancelled"
          and d.find_element(By.TAG_NAME, "body").get_attribute("data-live") == "ended" and _chart_points(d) == 3)
    assert driver.find_element(By.ID, "api-key").get_attribute("value") == "key-for-this-session"
    assert [r[3] for r in script.requests if r[1].endswith("/events")] == [None, "3", None]
    assert not driver.find_element(By.ID, "open-demo").is_displayed()

    # a job whose events answer 404 (a server without the route: the same error shape as any 404) is polled
    driver.get(f"{url}/jobs#{script.NO_EVENTS}")
    _wait(driver, "the job followed by polling", lambda d: d.find_element(By.TAG_NAME, "body").get_attribute(
        "data-live") == "polling" and _iteration(d) == 5 and _text(d, "job-id") == script.NO_EVENTS)
    assert _text(driver, "job-error") == "" and _text(driver, "job-state") == "running"
    polls = sum(r[1] == f"/v1/jobs/{script.NO_EVENTS}" for r in script.requests)
    _wait(driver, "a second poll", lambda d: sum(r[1] == f"/v1/jobs/{script.NO_EVENTS}" for r in script.requests)
          > polls + 1, timeout=5)
    unexpected = _unexpected_console(driver)
    assert not unexpected, unexpected


def test_a_finished_job_without_its_contact_sheet_says_why(driver, scripted):
    """The button stays disabled, and the page says the server's reason (the artefact's 404), not nothing."""
    script, url = scripted
    driver.get(f"{url}/jobs#{script.NO_SHEET}")
    _wait(driver, "the finished job", lambda d: _text(d, "job-state") == "succeeded"
          and d.find_element(By.ID, "artefact-note").is_displayed())
    contact = driver.find_element(By.ID, "download-contact")
    assert contact.get_attribute("disabled") is not None
    assert script.NO_SHEET_REASON in _text(driver, "artefact-note")
    assert "matplotlib is not installed" in contact.get_attribute("title"), contact.get_attribute("title")
    assert driver.find_element(By.ID, "download-report").is_enabled()
