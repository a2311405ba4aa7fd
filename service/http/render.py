"""Rendering over HTTP: ``POST /v1/render`` (one frame) and the WebSocket stream ``/v1/stream`` (RenderStream:
binary messages carry protobuf, text messages protobuf's JSON mapping)."""

from __future__ import annotations

import asyncio
import contextlib
import json
from typing import Any

from fastapi import APIRouter, Request, Response, WebSocket, WebSocketDisconnect
from google.protobuf import json_format
from google.protobuf.message import DecodeError

from blendsplat.v1 import render_pb2 as pb

from ..access.http import websocket_caller, websocket_subprotocol
from ..engine import AVATAR_ID_PATTERN
from ..errors import InvalidArgument, ServiceError, to_status
from ..openapi import render_request_schema
from .dependencies import Caller, RenderEngine, bounded_body

router = APIRouter(tags=["render"])
MEDIA_TYPES = {pb.CODEC_JPEG: "image/jpeg", pb.CODEC_PNG: "image/png", pb.CODEC_RAW_RGBA: "application/octet-stream",
               pb.CODEC_H264: "video/h264"}
_WS_CLOSE = {pb.OK: 1000, pb.UNAVAILABLE: 1012, pb.RESOURCE_EXHAUSTED: 1013, pb.INTERNAL: 1011}
FRAME_RESPONSE = {"description": "the frame, encoded as the codec asks", "content": {
    media: {"schema": {"type": "string", "format": "binary"}} for media in ("image/jpeg", "image/png",
                                                                            "application/octet-stream")},
    "headers": {"X-Blendsplat-Timings": {"description": "per-stage milliseconds (JSON)", "schema": {"type": "string"}}}}


def render_body(max_size: int) -> dict[str, Any]:
    """The OpenAPI request body of ``POST /v1/render`` (a RenderRequest in JSON, sizes up to ``max_size``)."""
    return {"required": True, "content": {"application/json": {
        "schema": render_request_schema(max_size, AVATAR_ID_PATTERN.pattern)}}}


def as_json(message) -> dict[str, Any]:
    return json_format.MessageToDict(message, always_print_fields_with_no_presence=True)


@router.post("/v1/render", summary="Render one frame",
             description="The body is a RenderRequest as JSON with its proto field names, e.g. {\"avatar_id\": "
                         "\"demo\", \"width\": 256, \"codec\": \"CODEC_PNG\", \"frame\": {\"index\": 1}} "
                         "(protobuf's camelCase names are accepted too; named coefficients are the avatar's "
                         "expression names: GET /v1/avatars/{id}). The answer is the encoded image; "
                         "X-Blendsplat-Timings holds the per-stage milliseconds.",
             response_class=Response, responses={200: FRAME_RESPONSE})
async def render_frame(request: Request, engine: RenderEngine, principal: Caller("render")) -> Response:
    body = await bounded_body(request, engine.settings.max_message_bytes)
    try:
        message = json_format.Parse(body or b"{}", pb.RenderRequest())
    except (json_format.ParseError, UnicodeDecodeError, RecursionError, ValueError, TypeError) as e:
        problem = "nested too deeply" if isinstance(e, RecursionError) else str(e)[:300]
        raise InvalidArgument(f"not a RenderRequest in JSON (UTF-8): {problem}", field="body") from None
    frame = await engine.render_once(message, principal)
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


@router.websocket("/v1/stream")
async def stream(ws: WebSocket, engine: RenderEngine) -> None:
    """RenderStream over a WebSocket: binary messages carry protobuf, text messages protobuf's JSON mapping."""
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
