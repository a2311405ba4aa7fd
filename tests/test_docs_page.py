"""/docs in headless Chromium, as a person sees it: Swagger UI (5.x, served from service/static/swagger/, no CDN)
renders the OpenAPI 3.1 document FastAPI publishes, lists the operations, and tries a call with the bearer key
entered in its Authorize dialog. Swagger UI 4 showed "Unable to render this definition" for 3.1.

Needs Debian's chromium and chromedriver (``apt-get install -y chromium chromium-driver``); skipped without them.
A screenshot is written to the test's tmp dir (and to $BLENDSPLAT_ARTIFACTS when set).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from conftest import LiveServer
from selenium import webdriver
from selenium.common.exceptions import TimeoutException
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

WAIT_S = 60
SWAGGER = Path(__file__).resolve().parents[1] / "service" / "static" / "swagger"


@pytest.fixture(scope="module")
def keyed(tmp_path_factory):
    """The service with keys on (the default): /docs is open, the calls it tries need the key."""
    server = LiveServer(tmp_path_factory.mktemp("docs"), auth="keys")
    yield server
    server.stop()


def _wait(drv: webdriver.Chrome, what: str, condition) -> object:
    try:
        return WebDriverWait(drv, WAIT_S, poll_frequency=0.1).until(condition)
    except TimeoutException:
        body = drv.find_element(By.TAG_NAME, "body").text[:2000]
        console = [f"{e['level']}: {e['message']}" for e in drv.get_log("browser")]
        pytest.fail(f"timed out after {WAIT_S} s waiting for {what}; page text: {body!r}; console: {console}")


def test_the_vendored_swagger_ui_is_5x_with_its_licence():
    version = (SWAGGER / "VERSION").read_text().strip()
    assert int(version.split(".")[0]) >= 5, version  # 4.x cannot read OpenAPI 3.1
    assert "Apache License" in (SWAGGER / "LICENSE").read_text()
    assert "swagger-ui-dist" in (SWAGGER / "fetch.sh").read_text()
    for name in ("swagger-ui-bundle.js.gz", "swagger-ui.css", "favicon-32x32.png", "NOTICE"):
        assert (SWAGGER / name).is_file(), name


def test_docs_list_the_operations_and_try_a_call_with_the_key(keyed, driver, tmp_path):
    driver.get(f"{keyed.http_url}/docs")
    _wait(driver, "the operations", lambda d: d.find_elements(By.CSS_SELECTOR, ".opblock-summary-path"))
    text = driver.find_element(By.TAG_NAME, "body").text
    assert "Unable to render" not in text, text[:1000]
    paths = {e.text.replace("\u200b", "") for e in driver.find_elements(By.CSS_SELECTOR, ".opblock-summary-path")}
    for path in ("/v1/avatars", "/v1/avatars/{avatar_id}", "/v1/render", "/v1/jobs", "/v1/jobs/{job_id}",
                 "/v1/uploads", "/healthz"):
        assert path in paths, sorted(paths)
    assert "OAS 3.1" in text
    # every resource the page loaded came from this server (no CDN, no network)
    origins = driver.execute_script("return performance.getEntriesByType('resource').map((e) => e.name);")
    assert origins and all(url.startswith(keyed.http_url) for url in origins), origins

    shot = tmp_path / "docs.png"
    assert driver.save_screenshot(str(shot)) and shot.stat().st_size > 10_000
    if artifacts := os.environ.get("BLENDSPLAT_ARTIFACTS"):
        Path(artifacts).mkdir(parents=True, exist_ok=True)
        shutil.copy(shot, Path(artifacts) / "docs.png")

    # Authorize with the bearer key, then try GET /v1/avatars: 200 with the demo avatar
    driver.find_element(By.CSS_SELECTOR, ".auth-wrapper .authorize").click()
    field = _wait(driver, "the Authorize dialog", lambda d: d.find_element(By.CSS_SELECTOR, ".modal-ux input"))
    field.send_keys(keyed.api_key)
    driver.find_element(By.CSS_SELECTOR, ".modal-ux .auth-btn-wrapper .authorize").click()
    driver.find_element(By.CSS_SELECTOR, ".modal-ux .auth-btn-wrapper .btn-done").click()
    driver.find_element(By.ID, "operations-avatars-list_avatars_v1_avatars_get").find_element(
        By.CSS_SELECTOR, ".opblock-summary-control").click()
    op = driver.find_element(By.ID, "operations-avatars-list_avatars_v1_avatars_get")
    _wait(driver, "Try it out", lambda d: op.find_element(By.CSS_SELECTOR, ".try-out__btn")).click()
    _wait(driver, "Execute", lambda d: op.find_element(By.CSS_SELECTOR, ".execute")).click()
    status = _wait(driver, "the live response", lambda d: op.find_elements(
        By.CSS_SELECTOR, ".live-responses-table .response .response-col_status"))
    assert status[0].text.strip() == "200", op.text[:2000]
    body = op.find_element(By.CSS_SELECTOR, ".live-responses-table").get_attribute("textContent")
    assert '"id": "demo"' in body, body[:1000]
