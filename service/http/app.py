"""The HTTP app: :func:`create_app` puts the routers together (avatars, render and the WebSocket stream,
adapters, operations, and the training jobs' routers when the process has a :class:`~service.jobs.training.Training`:
``serve`` and ``up`` always do), maps every error to the one JSON error shape (:func:`service.errors.http_error`;
request validation errors answer 422 naming the field) and makes the OpenAPI document exact
(:func:`service.openapi.document_errors`). JSON bodies are protobuf's canonical JSON mapping of the
``blendsplat.v1`` messages.

Every request passes one guard (:class:`RequestGuard`): a request body that sends nothing for
``body_timeout_seconds`` is refused (408), one still arriving when the server drains gets 503, both closing the
connection; and an exception nothing mapped answers a typed JSON 500 carrying an error id that the log line has
too (never plain text, never a traceback). Bodies are bounded before they are read: a declared length over the
route's limit answers 413 at once and closes the connection.
"""

from __future__ import annotations

import asyncio
import json
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import compile_path

from blendsplat.v1 import render_pb2 as pb

from ..access.http import OPEN_PATHS
from ..engine import Engine
from ..errors import BlendsplatError, BodyRefused, BodyTimeout, ServiceError, http_error, invalid_request
from ..jobs.api import ROUTERS as TRAINING_ROUTERS
from ..jobs.training import Training
from ..openapi import document_errors
from . import adapters, avatars, ops, render, tokens, webrtc


def error_response(exc: BaseException, where: str = "", metrics=None) -> JSONResponse:
    """Any exception as the HTTP answer :func:`service.errors.http_error` maps it to."""
    status, body, headers = http_error(exc, where, metrics)
    return JSONResponse(body, status_code=status, headers=headers or None)


def routes(app: FastAPI, items=None, prefix: str = "") -> list[tuple[str, Any]]:
    """Every route of ``app`` with its full path (FastAPI keeps an included router as one entry)."""
    out = []
    for route in app.routes if items is None else items:
        if hasattr(route, "original_router"):
            out += routes(app, route.original_router.routes, prefix + route.include_context.prefix)
        elif hasattr(route, "path"):
            out.append((prefix + route.path, route))
    return out


def _allowed_methods(app: FastAPI, path: str) -> list[str]:
    """Every method some route serves at ``path`` (a 405's ``Allow``: Starlette names only the first route's)."""
    if not hasattr(app.state, "method_table"):
        app.state.method_table = [(compile_path(full)[0], set(getattr(route, "methods", None) or ()))
                                  for full, route in routes(app)]
    allowed = set().union(*(methods for regex, methods in app.state.method_table if regex.match(path)))
    return sorted(allowed | ({"HEAD"} if "GET" in allowed else set()))


def _http_exception(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    """Starlette's own HTTP errors (no such route, method not allowed) in the one error shape, status kept."""
    code = {404: pb.NOT_FOUND, 503: pb.UNAVAILABLE}.get(exc.status_code, pb.INVALID_ARGUMENT)
    message = str(exc.detail)
    headers = dict(getattr(exc, "headers", None) or {})
    if exc.status_code == 400:  # FastAPI's "error parsing the body": an invalid request like any other (422)
        body = {"error": {"code": "INVALID_ARGUMENT", "message": f"the body is not valid JSON ({message})",
                          "field": "body"}}
        return JSONResponse(body, status_code=422)
    if exc.status_code == 405:
        allowed = _allowed_methods(request.app, request.url.path)
        headers["Allow"] = ", ".join(allowed)
        message = f"{request.method} is not served at {request.url.path[:200]}; it serves {', '.join(allowed)}"
    body = {"error": {"code": pb.Code.Name(code), "message": message, "field": ""}}
    return JSONResponse(body, status_code=exc.status_code, headers=headers or None)


class RequestGuard:
    """ASGI middleware over every HTTP request (WebSockets pass through):

    - the request body (a request that announces one), as the route reads it: a body that sends no bytes for
      ``body_timeout`` seconds raises :class:`~service.errors.BodyTimeout` (408), and one still arriving when
      ``closing`` is set (the server drains) raises :class:`~service.errors.BodyRefused` (503), inside the route,
      so what it was writing (an upload's temp file) is removed on the way out like for any other refusal;
    - an exception that no handler mapped: a typed JSON 500 (INTERNAL, an error id) and the traceback in the log
      under the same id, never uvicorn's plain-text 500.
    """

    def __init__(self, app, *, body_timeout: float, closing: asyncio.Event):
        self.app, self.body_timeout, self.closing = app, body_timeout, closing

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        body_done = not any(name == b"transfer-encoding" or (name == b"content-length" and value.strip().lstrip(b"0"))
                            for name, value in scope.get("headers", ()))  # no body announced: nothing to guard
        started = False

        async def guarded_receive():
            nonlocal body_done
            if body_done:  # after the body: only the disconnect is left to wait for, however long
                return await receive()
            if self.closing.is_set():
                raise BodyRefused("the server is shutting down; the request body was not finished", field="body")
            message_task = asyncio.ensure_future(receive())
            closing_task = asyncio.ensure_future(self.closing.wait())
            try:
                done, _ = await asyncio.wait((message_task, closing_task), timeout=self.body_timeout,
                                             return_when=asyncio.FIRST_COMPLETED)
            finally:
                closing_task.cancel()
            if message_task in done:
                message = message_task.result()
                body_done = message["type"] != "http.request" or not message.get("more_body", False)
                return message
            message_task.cancel()
            if closing_task in done:
                raise BodyRefused("the server is shutting down; the request body was not finished", field="body")
            raise BodyTimeout(f"no bytes of the request body arrived for {self.body_timeout:g} s", field="body")

        async def tracked_send(message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, guarded_receive, tracked_send)
        except Exception as exc:  # noqa: BLE001 - nothing mapped it: a typed 500, logged with its id
            response = error_response(exc, f"{scope.get('method', '')} {scope.get('path', '')}",  # logs it
                                      scope["app"].state.engine.metrics if "app" in scope else None)
            if started:  # too late for an answer: uvicorn closes the connection
                return
            await response(scope, receive, send)


def stop_reading_bodies(app: FastAPI) -> None:
    """Drain: every request body still arriving is refused with 503 (:class:`RequestGuard`)."""
    app.state.closing.set()


def _handle_errors(app: FastAPI, engine: Engine) -> None:
    """Every error in the one JSON shape, counted in the engine's metrics."""
    async def on_error(request: Request, exc: Exception) -> JSONResponse:
        return error_response(exc, metrics=engine.metrics)

    async def on_invalid(request: Request, exc: Exception) -> JSONResponse:
        return error_response(invalid_request(exc.errors()), metrics=engine.metrics)

    async def on_http_exception(request: Request, exc: Exception) -> JSONResponse:
        response = _http_exception(request, exc)
        code = json.loads(response.body)["error"]["code"]
        engine.metrics.errors.labels(code, "http").inc()
        return response

    app.add_exception_handler(ServiceError, on_error)
    app.add_exception_handler(BlendsplatError, on_error)
    app.add_exception_handler(RequestValidationError, on_invalid)
    app.add_exception_handler(StarletteHTTPException, on_http_exception)


def create_app(engine: Engine, training: Training | None = None) -> FastAPI:
    """The app over ``engine``; with ``training``, also the training jobs' routes (:mod:`service.jobs.api`)."""
    app = FastAPI(title="Blendsplat render service", version="1", docs_url=None, redoc_url=None,
                  description="Gaussian blendshape head avatars, animated and rendered live: list them "
                              "(/v1/avatars), render a frame (/v1/render) or stream frames (the WebSocket "
                              "/v1/stream). The gRPC service blendsplat.v1.RenderService carries the same messages. "
                              "Training jobs: upload a tracked video (/v1/uploads), submit a job (/v1/jobs), a "
                              "worker trains it.")
    app.state.engine = engine
    app.state.training = training
    app.state.problems = {}  # readiness check -> why it fails: a text, or a callable asked then (set by the process)
    app.state.closing = asyncio.Event()  # set by stop_reading_bodies (drain)
    app.state.webrtc = webrtc.Peers(engine)  # WebRTC sessions (service/webrtc/)
    for module in (avatars, render, adapters, ops, tokens, webrtc):
        app.include_router(module.router)
    # Swagger UI 5 (it reads OpenAPI 3.1), vendored from the npm package swagger-ui-dist: service/static/swagger/
    app.mount("/static/swagger", StaticFiles(directory=ops.SWAGGER), name="swagger-ui")
    app.mount("/static/app", StaticFiles(directory=ops.STATIC), name="pages")  # the pages' shared theme.css
    if training is not None:
        for router in TRAINING_ROUTERS:
            app.include_router(router)
    _handle_errors(app, engine)
    app.add_middleware(RequestGuard, body_timeout=engine.settings.body_timeout_seconds, closing=app.state.closing)
    if engine.settings.allowed_origins:  # browsers on other origins (the server's own pages need no CORS)
        app.add_middleware(CORSMiddleware, allow_origins=engine.settings.allowed_origins, allow_methods=["*"],
                           allow_headers=["Authorization", "Content-Type", "Idempotency-Key", "Last-Event-ID"],
                           expose_headers=["Location", "Link", "Retry-After", "X-Blendsplat-Timings"], max_age=600)
    document_errors(app, OPEN_PATHS, bodies={
        ("/v1/render", "post"): render.render_body(engine.settings.max_size),
        ("/v1/avatars/{avatar_id}", "put"): avatars.BUNDLE_BODY,
        ("/v1/adapters/{adapter_id}", "put"): adapters.ADAPTER_UPLOAD_BODY,
        ("/v1/webrtc", "post"): webrtc.offer_body(engine.settings.webrtc_max_offer_bytes),
        ("/v1/webrtc/{session_id}", "patch"): webrtc.fragment_body(engine.settings.webrtc_max_offer_bytes),
    })
    return app
