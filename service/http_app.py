"""The HTTP transport (FastAPI): REST for avatars and single frames, the WebSocket stream, health, metrics and the
/demo page. A thin adapter over the :class:`~service.engine.Engine`: JSON bodies are protobuf's canonical JSON
mapping of the ``blendsplat.v1`` messages, and errors map to HTTP statuses in :mod:`service.errors`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from pathlib import Path
from typing import Any

from fastapi import APIRouter, FastAPI, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, JSONResponse, Response
from google.protobuf import json_format
from google.protobuf.message import DecodeError
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from blendsplat.v1 import render_pb2 as pb
from render_core.errors import BlendsplatError

from .engine import Engine
from .errors import InvalidArgument, ServiceError, http_status, to_status

log = logging.getLogger(__name__)
STATIC = Path(__file__).parent / "static"
MEDIA_TYPES = {pb.CODEC_JPEG: "image/jpeg", pb.CODEC_PNG: "image/png", pb.CODEC_RAW_RGBA: "application/octet-stream",
               pb.CODEC_H264: "video/h264"}
_WS_CLOSE = {pb.OK: 1000, pb.UNAVAILABLE: 1012, pb.RESOURCE_EXHAUSTED: 1013, pb.INTERNAL: 1011}


def as_json(message) -> dict[str, Any]:
    return json_format.MessageToDict(message, always_print_fields_with_no_presence=True)


def _error_response(exc: BaseException) -> JSONResponse:
    status = to_status(exc)
    if status.code == pb.INTERNAL:
        log.exception("internal error", exc_info=exc)
    return JSONResponse({"error": as_json(status) | {"code": pb.Code.Name(status.code)}},
                        status_code=http_status(status.code))


def _engine(request: Request | WebSocket) -> Engine:
    return request.app.state.engine


# ------------------------------------------------------------------------------------------------------- avatars
avatars = APIRouter(prefix="/v1/avatars", tags=["avatars"])


@avatars.get("", summary="Avatars in the bundle store (and whether this replica has them loaded)")
async def list_avatars(request: Request) -> dict:
    return as_json(pb.ListAvatarsResponse(avatars=_engine(request).list_avatars()))


@avatars.get("/{avatar_id}", summary="Describe one avatar: counts, expression and joint names, precision")
async def get_avatar(avatar_id: str, request: Request) -> dict:
    return as_json(_engine(request).avatar_info(avatar_id))


@avatars.put("/{avatar_id}", status_code=201, summary="Upload (create or replace) an avatar bundle",
             description="The body is the bundle file (application/octet-stream). It is fully validated before it "
                         "replaces anything; an invalid or oversize upload leaves the store unchanged.")
async def put_avatar(avatar_id: str, request: Request) -> dict:
    declared = request.headers.get("content-length", "")  # a plain number, else the stream's size decides
    size = int(declared) if declared.isascii() and declared.isdigit() and len(declared) <= 18 else None
    return as_json(await _engine(request).replace(avatar_id, request.stream(), size))


@avatars.post("/{avatar_id}/load", summary="Load an avatar into this replica's cache")
async def load_avatar(avatar_id: str, request: Request) -> dict:
    return as_json(await _engine(request).load(avatar_id))


@avatars.post("/{avatar_id}/unload", summary="Drop an avatar from this replica's cache (the bundle stays)")
async def unload_avatar(avatar_id: str, request: Request) -> dict:
    return as_json(_engine(request).unload(avatar_id))


# --------------------------------------------------------------------------------------------------- rendering
render = APIRouter(tags=["render"])


@render.post("/v1/render", summary="Render one frame",
             description="The body is a RenderRequest in protobuf JSON, e.g. {\"avatarId\": \"demo\", \"width\": 512,"
                         " \"codec\": \"CODEC_PNG\", \"frame\": {\"namedCoefficients\": {\"exp_00\": 1}}}. The answer "
                         "is the encoded image; X-Blendsplat-Timings holds the per-stage milliseconds.",
             response_class=Response)
async def render_frame(request: Request) -> Response:
    body = await request.body()
    if len(body) > _engine(request).settings.max_message_bytes:
        raise InvalidArgument("the request is too large", field="body")
    try:
        message = json_format.Parse(body or b"{}", pb.RenderRequest())
    except json_format.ParseError as e:
        raise InvalidArgument(f"not a RenderRequest: {e}", field="body") from None
    frame = await _engine(request).render_once(message)
    return Response(frame.data, media_type=MEDIA_TYPES[frame.codec],
                    headers={"X-Blendsplat-Timings": json.dumps(as_json(frame.timings))})


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
    await ws.accept()
    json_mode = False

    async def send(reply: pb.StreamResponse) -> None:
        if json_mode:
            await ws.send_text(json_format.MessageToJson(reply, indent=None))
        else:
            await ws.send_bytes(reply.SerializeToString())

    async def refuse(exc: BaseException) -> None:
        status = to_status(exc)
        await send(pb.StreamResponse(status=status))
        await ws.close(_WS_CLOSE.get(status.code, 1008), status.message[:120])

    try:
        first, json_mode, problem = await _receive(ws)
        if first is None or first.WhichOneof("msg") != "open":
            return await refuse(InvalidArgument(problem or "the first message must open a session", field="open"))
        try:
            session = await engine.open(first.open, "websocket")
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


# ----------------------------------------------------------------------------------------------- operations
ops = APIRouter(tags=["operations"])


@ops.get("/healthz", summary="Liveness: the process answers")
async def healthz() -> dict:
    return {"status": "ok"}


@ops.get("/readyz", summary="Readiness: settings valid, bundle store reachable, warm-up frame rendered, not draining")
async def readyz(request: Request) -> JSONResponse:
    checks = _engine(request).readiness()
    ready = all(checks.values())
    return JSONResponse({"ready": ready, "checks": checks}, status_code=200 if ready else 503)


@ops.get("/metrics", summary="Prometheus metrics", response_class=Response)
async def metrics(request: Request) -> Response:
    return Response(generate_latest(_engine(request).metrics.registry), media_type=CONTENT_TYPE_LATEST)


@ops.get("/demo", summary="A page with sliders that drives an avatar over the WebSocket stream",
         response_class=FileResponse)
async def demo() -> FileResponse:
    return FileResponse(STATIC / "demo.html", media_type="text/html")


def create_app(engine: Engine) -> FastAPI:
    app = FastAPI(title="Blendsplat render service", version="1",
                  description="Gaussian blendshape head avatars, animated and rendered live. The gRPC service "
                              "blendsplat.v1.RenderService carries the same messages.")
    app.state.engine = engine
    for router in (avatars, render, ops):
        app.include_router(router)

    async def on_error(request: Request, exc: Exception) -> JSONResponse:
        return _error_response(exc)

    app.add_exception_handler(ServiceError, on_error)
    app.add_exception_handler(BlendsplatError, on_error)
    return app
