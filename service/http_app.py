"""The HTTP transport (FastAPI): REST for avatars and single frames, the WebSocket stream, health, metrics and the
/demo and /jobs pages. A thin adapter over the :class:`~service.engine.Engine`: JSON bodies are protobuf's
canonical JSON mapping of the ``blendsplat.v1`` messages, and errors map to HTTP statuses in :mod:`service.errors`.

The training jobs' routes (uploads, jobs, artefacts, deletion) are :mod:`service.jobs_api`'s, mounted here when the
process has a :class:`~service.jobs_api.Training` (``serve`` and ``up`` always do). Request validation errors
(pydantic) answer the same error shape as every other error: 422 naming the field.

Every request passes one guard (:class:`RequestGuard`): a request body that sends nothing for
``body_timeout_seconds`` is refused (408), one still arriving when the server drains gets 503, both closing the
connection; and an exception nothing mapped answers a typed JSON 500 carrying an error id that the log line has
too (never plain text, never a traceback). Bodies are bounded before they are read: a declared length over the
route's limit answers 413 at once and closes the connection.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import uuid
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from google.protobuf import json_format
from google.protobuf.message import DecodeError
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import compile_path
from swagger_ui_bundle import swagger_ui_path

from blendsplat.v1 import render_pb2 as pb
from render_core.errors import BlendsplatError

from .adapters import MAX_ADAPTER_BYTES, MAX_MANIFEST_BYTES
from .auth import Access, Unauthenticated
from .engine import AVATAR_ID_PATTERN, Engine
from .errors import InvalidArgument, ServiceError, Unavailable, http_status, to_status
from .http_auth import OPEN_PATHS, Caller, websocket_caller, websocket_subprotocol
from .jobs_api import ROUTERS as TRAINING_ROUTERS
from .jobs_api import Training
from .limits import RateLimited
from .openapi import document_errors, render_request_schema
from .uploads import UploadTooLarge

log = logging.getLogger(__name__)
STATIC = Path(__file__).parent / "static"
MEDIA_TYPES = {pb.CODEC_JPEG: "image/jpeg", pb.CODEC_PNG: "image/png", pb.CODEC_RAW_RGBA: "application/octet-stream",
               pb.CODEC_H264: "video/h264"}
_WS_CLOSE = {pb.OK: 1000, pb.UNAVAILABLE: 1012, pb.RESOURCE_EXHAUSTED: 1013, pb.INTERNAL: 1011}


def as_json(message) -> dict[str, Any]:
    return json_format.MessageToDict(message, always_print_fields_with_no_presence=True)


class BodyTooLarge(InvalidArgument):
    """HTTP only: a request body over its route's limit (413; the connection is closed, the rest never read)."""


class BodyTimeout(InvalidArgument):
    """HTTP only: a request body that stalled (408; the connection is closed)."""


class BodyRefused(Unavailable):
    """A request body still arriving when the server drains (503; the connection is closed)."""


# HTTP only: these are INVALID_ARGUMENT on the wire, with their own HTTP statuses.
_HTTP_ONLY = ((UploadTooLarge, 413), (BodyTooLarge, 413), (BodyTimeout, 408))
# The body was not read to its end: close the connection rather than read and discard the rest.
_CLOSE = (BodyTooLarge, BodyTimeout, BodyRefused)


def _error_response(exc: BaseException, where: str = "", metrics=None) -> JSONResponse:
    status = to_status(exc)
    if metrics is not None:
        metrics.errors.labels(pb.Code.Name(status.code), "http").inc()
    body = {"error": {"code": pb.Code.Name(status.code), "message": status.message, "field": status.field}}
    if status.code == pb.INTERNAL:
        error_id = uuid.uuid4().hex[:16]
        log.error("internal error %s%s: %s: %s", error_id, f" ({where})" if where else "", type(exc).__name__,
                  exc, exc_info=exc)
        body["error"]["message"] = f"{status.message}; error id {error_id}"
        body["error"]["errorId"] = error_id
    http = next((code for kind, code in _HTTP_ONLY if isinstance(exc, kind)), None) or http_status(status.code)
    headers = {"Connection": "close"} if isinstance(exc, _CLOSE) else {}
    if isinstance(exc, RateLimited):
        headers["Retry-After"] = str(exc.retry_after)
    if isinstance(exc, Unauthenticated):
        headers["WWW-Authenticate"] = 'Bearer realm="blendsplat"'
    return JSONResponse(body, status_code=http, headers=headers or None)


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
      ``body_timeout`` seconds raises :class:`BodyTimeout` (408), and one still arriving when ``closing`` is set
      (the server drains) raises :class:`BodyRefused` (503), inside the route, so what it was writing (an upload's
      temp file) is removed on the way out like for any other refusal;
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
            response = _error_response(exc, f"{scope.get('method', '')} {scope.get('path', '')}",  # logs it
                                       scope["app"].state.engine.metrics if "app" in scope else None)
            if started:  # too late for an answer: uvicorn closes the connection
                return
            await response(scope, receive, send)


def stop_reading_bodies(app: FastAPI) -> None:
    """Drain: every request body still arriving is refused with 503 (:class:`RequestGuard`)."""
    app.state.closing.set()


def _validation_error(exc: RequestValidationError) -> InvalidArgument:
    """FastAPI's request validation error as the service's INVALID_ARGUMENT, naming the first field at fault
    (``iterations``, ``limit``, ``idempotency-key``; the location's kind, body or query, left out)."""
    errors = exc.errors()
    first = errors[0] if errors else {}
    location = [str(part) for part in first.get("loc", ())]
    field = ".".join(location[1:]) if len(location) > 1 else (location[0] if location else "body")
    message = str(first.get("msg", "invalid request"))
    if len(errors) > 1:
        message += f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})"
    return InvalidArgument(message, field=field)


def _engine(request: Request | WebSocket) -> Engine:
    return request.app.state.engine


# ------------------------------------------------------------------------------------------------------- avatars
avatars = APIRouter(prefix="/v1/avatars", tags=["avatars"])
AvatarId = Annotated[str, PathParam(pattern=AVATAR_ID_PATTERN.pattern, max_length=128, examples=["demo"],
                                    description="an avatar id: letters, digits, '.', '_', '-' (at most 128, "
                                                "starting with a letter or digit)")]


class AvatarOut(BaseModel):
    """An avatar as REST answers it: blendsplat.v1.AvatarInfo with its proto field names and plain numbers."""

    id: str
    loaded: bool = Field(description="in this replica's cache")
    gaussians: int = Field(description="face + mouth")
    mouth_gaussians: int
    expression_names: list[str]
    joint_names: list[str]
    sh_degree: int
    precision: str = Field(description="blendshape storage: fp32 or fp16")
    face_model: str
    file_bytes: int
    memory_bytes: int = Field(description="resident in this replica's cache (0 when not loaded)")
    digest: str = Field(description="sha256 of the bundle's content")

    @classmethod
    def of(cls, info: pb.AvatarInfo) -> AvatarOut:
        return cls(**{name: getattr(info, name) for name in cls.model_fields})


class AvatarList(BaseModel):
    avatars: list[AvatarOut]


@avatars.get("", response_model=AvatarList,
             summary="Avatars in the bundle store (and whether this replica has them loaded)")
async def list_avatars(request: Request, principal: Caller("render")) -> AvatarList:
    return AvatarList(avatars=[AvatarOut.of(a) for a in _engine(request).list_avatars(principal)])


@avatars.get("/{avatar_id}", response_model=AvatarOut,
             summary="Describe one avatar: counts, expression and joint names, precision")
async def get_avatar(avatar_id: AvatarId, request: Request, principal: Caller("render")) -> AvatarOut:
    return AvatarOut.of(_engine(request).avatar_info(avatar_id, principal))


@avatars.put("/{avatar_id}", status_code=201, response_model=AvatarOut,
             summary="Upload (create or replace) an avatar bundle",
             description="The body is the bundle file (any Content-Type). It is fully validated before it "
                         "replaces anything; an invalid or oversize upload leaves the store unchanged.")
async def put_avatar(avatar_id: AvatarId, request: Request, principal: Caller("avatars:write")) -> AvatarOut:
    declared = request.headers.get("content-length", "")  # a plain number, else the stream's size decides
    size = int(declared) if declared.isascii() and declared.isdigit() and len(declared) <= 18 else None
    return AvatarOut.of(await _engine(request).replace(avatar_id, request.stream(), size, principal))


@avatars.delete("/{avatar_id}", status_code=204, response_class=Response,
                summary="Delete an avatar: its bundle, the files beside it, and this replica's cached copy",
                description="Streams already open on it keep their copy until they end; new ones get NOT_FOUND.")
async def delete_avatar(avatar_id: AvatarId, request: Request, principal: Caller("avatars:write")) -> Response:
    await _engine(request).delete(avatar_id, principal)
    return Response(status_code=204)


@avatars.post("/{avatar_id}/load", response_model=AvatarOut, summary="Load an avatar into this replica's cache")
async def load_avatar(avatar_id: AvatarId, request: Request, principal: Caller("render")) -> AvatarOut:
    return AvatarOut.of(await _engine(request).load(avatar_id, principal))


@avatars.post("/{avatar_id}/unload", response_model=AvatarOut,
              summary="Drop an avatar from this replica's cache (the bundle stays)")
async def unload_avatar(avatar_id: AvatarId, request: Request, principal: Caller("avatars:write")) -> AvatarOut:
    return AvatarOut.of(_engine(request).unload(avatar_id, principal))


# --------------------------------------------------------------------------------------------------- rendering
render = APIRouter(tags=["render"])


FRAME_RESPONSE = {"description": "the frame, encoded as the codec asks", "content": {
    media: {"schema": {"type": "string", "format": "binary"}} for media in ("image/jpeg", "image/png",
                                                                            "application/octet-stream")},
    "headers": {"X-Blendsplat-Timings": {"description": "per-stage milliseconds (JSON)", "schema": {"type": "string"}}}}


@render.post("/v1/render", summary="Render one frame",
             description="The body is a RenderRequest as JSON with its proto field names, e.g. {\"avatar_id\": "
                         "\"demo\", \"width\": 256, \"codec\": \"CODEC_PNG\", \"frame\": {\"index\": 1}} "
                         "(protobuf's camelCase names are accepted too; named coefficients are the avatar's "
                         "expression names: GET /v1/avatars/{id}). The answer is the encoded image; "
                         "X-Blendsplat-Timings holds the per-stage milliseconds.",
             response_class=Response, responses={200: FRAME_RESPONSE})
async def render_frame(request: Request, principal: Caller("render")) -> Response:
    limit = _engine(request).settings.max_message_bytes
    body = await _bounded_body(request, limit)
    try:
        message = json_format.Parse(body or b"{}", pb.RenderRequest())
    except (json_format.ParseError, UnicodeDecodeError, RecursionError, ValueError, TypeError) as e:
        problem = "nested too deeply" if isinstance(e, RecursionError) else str(e)[:300]
        raise InvalidArgument(f"not a RenderRequest in JSON (UTF-8): {problem}", field="body") from None
    frame = await _engine(request).render_once(message, principal)
    return Response(frame.data, media_type=MEDIA_TYPES[frame.codec],
                    headers={"X-Blendsplat-Timings": json.dumps(as_json(frame.timings))})


async def _bounded_body(request: Request, limit: int) -> bytes:
    """The request body, refused before it is read when its declared length passes ``limit`` and as soon as the
    bytes received do (a body without a length is counted as it arrives): never more than ``limit`` in memory."""
    declared = request.headers.get("content-length")
    if declared is not None and (not declared.isdigit() or int(declared) > limit):
        raise BodyTooLarge(f"the request body is {declared[:20]} bytes; the limit is {limit}", field="body")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise BodyTooLarge(f"the request body exceeds the limit of {limit} bytes", field="body")
        chunks.append(chunk)
    return b"".join(chunks)


async def _receive(ws: WebSocket) -> tuple[pb.StreamRequest | None, bool, str | None]:
    """The next client message: (request or None if unparsable, was JSON, parse error). Raises on disconnect."""
    msg = await ws.receive()
    if msg["type"] == "websocket.disconnect":
        raise WebSocketDisconnect(msg.get("code", 1000))
    text, data = msg.get("text"), msg.get("bytes")
    try:
        if text is not None:
            return json_format.Parse(text, pb.StreamRequest()), True, None
        return pb.StreamRequest.FromString(data or b""), False, None
    except (json_format.ParseError, DecodeError) as e:
        return None, text is not None, f"not a blendsplat.v1.StreamRequest: {e}"


@render.websocket("/v1/stream")
async def stream(ws: WebSocket) -> None:
    """RenderStream over a WebSocket: binary messages carry protobuf, text messages protobuf's JSON mapping."""
    engine = _engine(ws)
    try:
        principal, refused = await websocket_caller(ws, "render"), None
    except ServiceError as e:  # told in the stream (after its first message: JSON or binary), then closed
        principal, refused = None, e
    await ws.accept(subprotocol=websocket_subprotocol(ws))
    json_mode = False

    async def send(reply: pb.StreamResponse) -> None:
        if json_mode:
            await ws.send_text(json_format.MessageToJson(reply, indent=None))
        else:
            await ws.send_bytes(reply.SerializeToString())

    async def refuse(exc: BaseException) -> None:
        status = to_status(exc)
        engine.metrics.errors.labels(pb.Code.Name(status.code), "websocket").inc()
        await send(pb.StreamResponse(status=status))
        await ws.close(_WS_CLOSE.get(status.code, 1008), status.message[:120])

    try:
        first, json_mode, problem = await _receive(ws)
        if refused is not None:
            return await refuse(refused)
        if first is None or first.WhichOneof("msg") != "open":
            return await refuse(InvalidArgument(problem or "the first message must open a session", field="open"))
        try:
            session = await engine.open(first.open, "websocket", principal)
        except Exception as e:  # noqa: BLE001 - mapped to a status
            return await refuse(e)
    except WebSocketDisconnect:
        return

    async def pump() -> None:
        try:
            while True:
                request, _, problem = await _receive(ws)
                if request is None:
                    session.error(to_status(InvalidArgument(problem, field="message")))
                else:
                    session.handle(request)
        except (WebSocketDisconnect, RuntimeError):
            engine.close_session(session)

    reader = asyncio.create_task(pump())
    final = pb.OK
    try:
        await send(session.header())
        async for reply in session.responses():
            await send(reply)
            if reply.HasField("status"):
                final = reply.status.code
        with contextlib.suppress(RuntimeError):
            await ws.close(_WS_CLOSE.get(final, 1008))
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        reader.cancel()
        engine.close_session(session)


# ------------------------------------------------------------------------------------------------------ adapters
adapters = APIRouter(prefix="/v1/adapters", tags=["adapters"])
AdapterId = Annotated[str, PathParam(pattern=AVATAR_ID_PATTERN.pattern, max_length=128,
                                     description="an adapter id (the same rule as avatar ids)")]
_ADAPTER_UPLOAD = MAX_ADAPTER_BYTES + MAX_MANIFEST_BYTES + (1 << 20)  # the two parts' limits, plus framing


class AdapterSource(BaseModel):
    convention: str = Field(description="the source's naming: arkit-52, flame or custom")
    face_model: str = Field(description="the tracker's face model, or empty")
    names: list[str] = Field(description="the model's inputs in order: expression names, and <joint>.x/.y/.z for a "
                                         "source joint's axis-angle components")


Bound = float | Literal["inf", "-inf"]  # JSON has no infinity


class AdapterTarget(BaseModel):
    face_model: str = Field(description="the avatars it drives have this face model")
    expression_names: list[str]
    joint_names: list[str]
    expression_min: list[Bound] | None = Field(description="the clamp the model applies, per target expression")
    expression_max: list[Bound] | None


class AdapterManifestOut(BaseModel):
    """The adapter manifest (docs/method.md section 12)."""

    format: Literal["blendsplat-adapter"]
    version: int
    id: str
    source: AdapterSource
    target: AdapterTarget
    opset: int
    provenance: dict[str, Any] = Field(description="how it was made (free-form)")


class AdapterOut(BaseModel):
    id: str
    tenant: str | None = Field(description="the owning tenant; null: the deployment's (every key may use it)")
    model_bytes: int
    model_sha256: str
    manifest: AdapterManifestOut


class AdapterList(BaseModel):
    adapters: list[AdapterOut]


@adapters.get("", response_model=AdapterList,
              summary="Retargeting adapters in the store (ONNX models mapping a tracker's coefficients to a face "
                      "model's)")
async def list_adapters(request: Request, principal: Caller("render")) -> dict:
    return {"adapters": [a for a in _engine(request).adapters.list()
                         if principal.may_read(a.get("tenant"), a.get("tenant") is None)]}


@adapters.get("/{adapter_id}", response_model=AdapterOut,
              summary="One adapter: its manifest (source and target names), owner, size, digest")
async def get_adapter(adapter_id: AdapterId, request: Request, principal: Caller("render")) -> dict:
    info = _engine(request).adapters.info(adapter_id)
    principal.check_read(f"adapter {adapter_id!r}", info.get("tenant"), info.get("tenant") is None)
    return info


@adapters.put("/{adapter_id}", status_code=201, response_model=AdapterOut,
              summary="Upload (create or replace) a retargeting adapter",
              description="multipart/form-data with two parts: `manifest` (the JSON manifest, docs/method.md "
                          "section 12; its id may be left out) and `model` (the .onnx file), e.g. curl -X PUT -F "
                          "manifest=@m.json -F model=@a.onnx. Both are validated (size, opsets, operators, no "
                          "external data, shapes against the manifest, loads in onnxruntime) before anything is "
                          "stored; a refusal is 422 naming the reason's field.")
async def put_adapter(adapter_id: AdapterId, request: Request, principal: Caller("avatars:write")) -> dict:
    _check_adapter_write(request, adapter_id, principal)
    body = await _bounded_body(request, _ADAPTER_UPLOAD)  # read once, bounded; the form parses these bytes

    async def replay() -> dict:
        return {"type": "http.request", "body": body, "more_body": False}

    try:
        form = await Request(request.scope, replay).form(max_files=2, max_fields=2, max_part_size=_ADAPTER_UPLOAD)
    except Exception as e:  # noqa: BLE001 - python-multipart's and starlette's parse errors
        raise InvalidArgument(f"not a multipart/form-data body with manifest and model parts ({type(e).__name__})",
                              field="body") from None
    parts = {}
    for name in ("manifest", "model"):
        part = form.get(name)
        if part is None:
            raise InvalidArgument(f"the {name} part is missing", field=name)
        parts[name] = part.encode() if isinstance(part, str) else await part.read()
    info = await asyncio.to_thread(_engine(request).adapters.put, adapter_id, parts["model"], parts["manifest"],
                                   None if principal.admin else principal.tenant)
    Access.audit(principal, "adapter.put", adapter_id)
    return info


ADAPTER_UPLOAD_BODY = {"required": True, "description": "the adapter: its manifest and its ONNX model", "content": {
    "multipart/form-data": {
        "schema": {"type": "object", "required": ["manifest", "model"], "properties": {
            "manifest": {"type": "string", "format": "binary",
                         "description": "the manifest, JSON (docs/method.md section 12)"},
            "model": {"type": "string", "format": "binary", "maxLength": MAX_ADAPTER_BYTES,
                      "description": "the ONNX model (opset 13-21, the allowed operators, no external data)"}}},
        "encoding": {"manifest": {"contentType": "application/json"},
                     "model": {"contentType": "application/octet-stream"}}}}}


def _check_adapter_write(request: Request, adapter_id: str, principal) -> None:
    """Adapters without a tenant are the deployment's (every key may use them; admin keys change them)."""
    try:
        info = _engine(request).adapters.info(adapter_id)
    except ServiceError:
        return  # a new id (or an invalid one, refused by the store with its reason)
    principal.check_write(f"adapter {adapter_id!r}", info.get("tenant"))


@adapters.delete("/{adapter_id}", response_model=AdapterOut,
                 summary="Delete an adapter (sessions using it keep their loaded copy); answers what was deleted")
async def delete_adapter(adapter_id: AdapterId, request: Request, principal: Caller("avatars:write")) -> dict:
    _check_adapter_write(request, adapter_id, principal)
    Access.audit(principal, "adapter.delete", adapter_id)
    return _engine(request).adapters.delete(adapter_id)


# ----------------------------------------------------------------------------------------------- operations
ops = APIRouter(tags=["operations"])
PAGE = {200: {"content": {"text/html": {"schema": {"type": "string"}}}, "description": "the page"}}


class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    ready: bool
    checks: dict[str, bool] = Field(description="each readiness check by name (settings, bundle_store, warm_up, "
                                               "not_draining, job_database...)")
    reasons: dict[str, str] | None = Field(None, description="when not ready: why, for each failing check")


@ops.get("/healthz", response_model=Health, summary="Liveness: the process answers")
async def healthz() -> dict:
    return {"status": "ok"}


@ops.get("/readyz", response_model=Readiness,
         responses={503: {"model": Readiness, "description": "not ready: the reasons, check by check"}},
         summary="Readiness: settings valid, bundle store reachable, warm-up frame rendered, not draining")
async def readyz(request: Request) -> JSONResponse:
    checks = _engine(request).readiness()
    ready = all(checks.values())
    body: dict[str, Any] = {"ready": ready, "checks": checks}
    if not ready:  # why, check by check (the process registers its reasons: texts, or callables asked now)
        known = {"not_draining": "the server is shutting down", "warm_up": "the warm-up frame is not rendered yet",
                 **request.app.state.problems}
        reasons = {name: known.get(name, "failed") for name, ok in checks.items() if not ok}
        body["reasons"] = {name: (why() if callable(why) else why) or "failed" for name, why in reasons.items()}
    return JSONResponse(body, status_code=200 if ready else 503)


@ops.get("/metrics", summary="Prometheus metrics", response_class=Response,
         responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                          "description": "the Prometheus text exposition format"}})
async def metrics(request: Request) -> Response:
    # off the event loop: the job metrics query the job database when scraped
    body = await asyncio.to_thread(generate_latest, _engine(request).metrics.registry)
    return Response(body, media_type=CONTENT_TYPE_LATEST)


@ops.get("/favicon.ico", include_in_schema=False)
async def favicon() -> Response:
    return Response(status_code=204)  # no icon; browsers stop asking without logging a 404


@ops.get("/docs", include_in_schema=False)
async def api_docs() -> Response:
    """Swagger UI from this server's own copy (swagger-ui-bundle): the docs work without internet."""
    return get_swagger_ui_html(openapi_url="/openapi.json", title="Blendsplat API",
                               swagger_js_url="/static/swagger/swagger-ui-bundle.js",
                               swagger_css_url="/static/swagger/swagger-ui.css",
                               swagger_favicon_url="/static/swagger/favicon-32x32.png")


@ops.get("/demo", summary="A page with sliders that drives an avatar over the WebSocket stream",
         response_class=FileResponse, responses=PAGE)
async def demo() -> FileResponse:
    return FileResponse(STATIC / "demo.html", media_type="text/html")


@ops.get("/jobs", summary="A page to upload a dataset, start a training job, watch it learn live, cancel, delete, "
                          "and open the trained avatar in /demo", response_class=FileResponse, responses=PAGE)
async def jobs_page() -> FileResponse:
    return FileResponse(STATIC / "jobs.html", media_type="text/html")


def create_app(engine: Engine, training: Training | None = None) -> FastAPI:
    """The app over ``engine``; with ``training``, also the training jobs' routes (:mod:`service.jobs_api`)."""
    app = FastAPI(title="Blendsplat render service", version="1", docs_url=None, redoc_url=None,
                  description="Gaussian blendshape head avatars, animated and rendered live. The gRPC service "
                              "blendsplat.v1.RenderService carries the same messages. Training jobs: upload a "
                              "tracked video (/v1/uploads), submit a job (/v1/jobs), a worker trains it.")
    app.state.engine = engine
    app.state.training = training
    app.state.problems = {}  # readiness check -> why it fails: a text, or a callable asked then (set by the process)
    app.state.closing = asyncio.Event()  # set by stop_reading_bodies (drain)
    for router in (avatars, render, adapters, ops):
        app.include_router(router)
    app.mount("/static/swagger", StaticFiles(directory=swagger_ui_path), name="swagger-ui")
    app.mount("/static/app", StaticFiles(directory=STATIC), name="pages")  # the pages' shared theme.css
    if training is not None:
        for router in TRAINING_ROUTERS:
            app.include_router(router)

    async def on_error(request: Request, exc: Exception) -> JSONResponse:
        return _error_response(exc, metrics=engine.metrics)

    async def on_invalid(request: Request, exc: Exception) -> JSONResponse:
        return _error_response(_validation_error(exc), metrics=engine.metrics)

    async def on_http_exception(request: Request, exc: Exception) -> JSONResponse:
        response = _http_exception(request, exc)
        code = json.loads(response.body)["error"]["code"]
        engine.metrics.errors.labels(code, "http").inc()
        return response

    app.add_exception_handler(ServiceError, on_error)
    app.add_exception_handler(BlendsplatError, on_error)
    app.add_exception_handler(RequestValidationError, on_invalid)
    app.add_exception_handler(StarletteHTTPException, on_http_exception)
    app.add_middleware(RequestGuard, body_timeout=engine.settings.body_timeout_seconds, closing=app.state.closing)
    if engine.settings.allowed_origins:  # browsers on other origins (the server's own pages need no CORS)
        app.add_middleware(CORSMiddleware, allow_origins=engine.settings.allowed_origins, allow_methods=["*"],
                           allow_headers=["Authorization", "Content-Type", "Idempotency-Key", "Last-Event-ID"],
                           expose_headers=["Location", "Retry-After", "X-Blendsplat-Timings"], max_age=600)
    bundle = {"schema": {"type": "string", "format": "binary"}}  # any bytes: the server validates the bundle
    document_errors(app, OPEN_PATHS, bodies={
        ("/v1/render", "post"): {"required": True, "content": {"application/json": {
            "schema": render_request_schema(engine.settings.max_size, AVATAR_ID_PATTERN.pattern)}}},
        ("/v1/avatars/{avatar_id}", "put"): {"required": True, "content": {"application/octet-stream": bundle},
                                             "description": "the bundle file (safetensors, schema 2)"},
        ("/v1/adapters/{adapter_id}", "put"): ADAPTER_UPLOAD_BODY,
    })
    return app
