"""Operations and pages: liveness, readiness (with its reasons), Prometheus metrics, the Swagger UI, and the /demo
and /jobs pages. None of them needs a key (:data:`service.access.http.OPEN_PATHS`)."""

from __future__ import annotations

import asyncio
import functools
from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ..errors import redact
from .dependencies import RenderEngine
from .schemas import Health, Readiness

router = APIRouter(tags=["operations"])
STATIC = Path(__file__).resolve().parents[1] / "static"
# Swagger UI 5.x (swagger-ui-dist from npm; VERSION, LICENSE and fetch.sh there): it reads the OpenAPI 3.1 document
# FastAPI publishes, which Swagger UI 4 cannot ("Unable to render this definition")
SWAGGER = STATIC / "swagger"
PAGE = {200: {"content": {"text/html": {"schema": {"type": "string"}}}, "description": "the page"}}


@router.get("/healthz", response_model=Health, summary="Liveness: the process answers")
async def healthz() -> dict:
    return {"status": "ok"}


@router.get("/readyz", response_model=Readiness,
            responses={503: {"model": Readiness, "description": "not ready: the reasons, check by check"}},
            summary="Readiness: settings valid, bundle store reachable, warm-up frame rendered, not draining")
async def readyz(request: Request, engine: RenderEngine) -> JSONResponse:
    checks = engine.readiness()
    ready = all(checks.values())
    body: dict[str, Any] = {"ready": ready, "checks": checks}
    if not ready:  # why, check by check (the process registers its reasons: texts, or callables asked now)
        known = {"not_draining": "the server is shutting down", "warm_up": "the warm-up frame is not rendered yet",
                 **request.app.state.problems}
        reasons = {name: known.get(name, "failed") for name, ok in checks.items() if not ok}
        body["reasons"] = {name: redact((why() if callable(why) else why) or "failed")  # no server path: no key here
                           for name, why in reasons.items()}
    return JSONResponse(body, status_code=200 if ready else 503)


@router.get("/metrics", summary="Prometheus metrics", response_class=Response,
            responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                             "description": "the Prometheus text exposition format"}})
async def metrics(engine: RenderEngine) -> Response:
    # off the event loop: the job metrics query the job database when scraped
    body = await asyncio.to_thread(generate_latest, engine.metrics.registry)
    return Response(body, media_type=CONTENT_TYPE_LATEST)


@router.get("/favicon.ico", include_in_schema=False)
async def favicon() -> Response:
    return Response(status_code=204)  # no icon; browsers stop asking without logging a 404


@router.get("/static/swagger/swagger-ui-bundle.js", include_in_schema=False)
async def swagger_bundle() -> Response:
    """Swagger UI's script, stored gzipped (458 KB instead of 1.7 MB in the package) and sent as it is stored
    (``Content-Encoding: gzip``, which every browser reads)."""
    return Response(_swagger_bundle(), media_type="application/javascript",
                    headers={"Content-Encoding": "gzip", "Cache-Control": "public, max-age=86400"})


@functools.lru_cache(maxsize=1)
def _swagger_bundle() -> bytes:
    return (SWAGGER / "swagger-ui-bundle.js.gz").read_bytes()


@router.get("/docs", include_in_schema=False)
async def api_docs() -> Response:
    """Swagger UI from this server's own copy (:data:`SWAGGER`): the docs work without internet."""
    return get_swagger_ui_html(openapi_url="/openapi.json", title="Blendsplat API",
                               swagger_js_url="/static/swagger/swagger-ui-bundle.js",
                               swagger_css_url="/static/swagger/swagger-ui.css",
                               swagger_favicon_url="/static/swagger/favicon-32x32.png")


@router.get("/demo", summary="A page with sliders that drives an avatar over the WebSocket stream",
            response_class=FileResponse, responses=PAGE)
async def demo() -> FileResponse:
    return FileResponse(STATIC / "demo.html", media_type="text/html")


@router.get("/jobs", summary="A page to upload a dataset, start a training job, watch it learn live, cancel, "
                             "delete, and open the trained avatar in /demo", response_class=FileResponse,
            responses=PAGE)
async def jobs_page() -> FileResponse:
    return FileResponse(STATIC / "jobs.html", media_type="text/html")
