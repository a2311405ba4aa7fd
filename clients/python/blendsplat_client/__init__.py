"""Blendsplat's Python client: render streams over gRPC and the REST API (avatars, adapters, uploads, training
jobs), sync (:class:`Client`) and asyncio (:class:`AsyncClient`) of the same shape.

    from blendsplat_client import Client

    with Client() as client:                      # $BLENDSPLAT_URL, $BLENDSPLAT_GRPC_TARGET, $BLENDSPLAT_API_KEY
        with client.stream("demo", size=256) as s:
            s.send(expression={"jawOpen": 0.5})
            frame = s.receive()                   # frame.image: numpy with the media extra; frame.data: bytes

Errors are typed (:mod:`blendsplat_client.errors`) and carry the service's status (code, message, field).
"""

from . import errors
from ._astream import AsyncStream
from ._config import RetryPolicy
from ._sse import Event
from ._stream import Frame, Stream
from .aio import AsyncClient
from .client import Client
from .errors import BlendsplatError, NotFound, Status

__all__ = ["AsyncClient", "AsyncStream", "BlendsplatError", "Client", "Event", "Frame", "NotFound", "RetryPolicy",
           "Status", "Stream", "errors"]
__version__ = "0.1.0"
