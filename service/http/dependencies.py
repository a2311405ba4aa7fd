"""What the HTTP routes take from the request: the engine (``engine: RenderEngine``), the caller
(``principal: Caller("render")``, :mod:`service.access.http`) and a body read within a limit (:func:`bounded_body`)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from starlette.requests import HTTPConnection

from ..access.http import Caller
from ..engine import Engine
from ..errors import BodyTooLarge
from ..intake import declared_length

__all__ = ["Caller", "RenderEngine", "bounded_body", "engine_of"]


def engine_of(connection: HTTPConnection) -> Engine:
    """The process's engine (a request's or a WebSocket's)."""
    return connection.app.state.engine


RenderEngine = Annotated[Engine, Depends(engine_of)]


async def bounded_body(request: Request, limit: int) -> bytes:
    """The request body, refused before it is read when its declared length passes ``limit`` and as soon as the
    bytes received do (a body without a length is counted as it arrives): never more than ``limit`` in memory."""
    declared = declared_length(request.headers)
    if declared is not None and declared > limit:
        raise BodyTooLarge(f"the request body is {declared} bytes; the limit is {limit}", field="body")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise BodyTooLarge(f"the request body exceeds the limit of {limit} bytes", field="body")
        chunks.append(chunk)
    return b"".join(chunks)
