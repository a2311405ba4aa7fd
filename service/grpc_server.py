"""The gRPC transport (grpc.aio): blendsplat.v1.RenderService, grpc.health.v1 and server reflection.

A thin adapter: every call goes to the :class:`~service.engine.Engine`; every RPC's errors become status codes
through :func:`status_on_error` and the one mapping in :mod:`service.errors` (INVALID_ARGUMENT naming the field,
NOT_FOUND, RESOURCE_EXHAUSTED, FAILED_PRECONDITION, UNAVAILABLE; anything else INTERNAL, logged).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import TypeVar

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection, reflection_pb2

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc

from .access.auth import Principal, bearer
from .engine import Engine
from .errors import InvalidArgument, grpc_code, to_status
from .metrics import Metrics

log = logging.getLogger(__name__)
SERVICE_NAME = pb.DESCRIPTOR.services_by_name["RenderService"].full_name
Reply = TypeVar("Reply")
STATUS_TRAILER = "blendsplat-status-bin"  # a failed call's blendsplat.v1.Status, serialized


@contextlib.asynccontextmanager
async def status_on_error(context: grpc.aio.ServicerContext, metrics: Metrics | None = None
                          ) -> AsyncIterator[None]:
    """End the call with the status of any error raised inside: its code from :func:`service.errors.to_status`,
    its details ``"field: message"`` (gRPC has no field slot), and the whole ``blendsplat.v1.Status`` (code,
    message, field) in the trailing metadata ``blendsplat-status-bin``: the same message a WebSocket client gets
    for a failed open. Errors that are not typed are INTERNAL, logged."""
    try:
        yield
    except grpc.aio.AbortError:
        raise  # already a status
    except Exception as exc:  # noqa: BLE001 - every failure becomes a status
        status = to_status(exc)
        if metrics is not None:
            metrics.errors.labels(pb.Code.Name(status.code), "grpc").inc()
        if status.code == pb.INTERNAL:
            log.exception("internal error", exc_info=exc)
        details = f"{status.field}: {status.message}" if status.field else status.message
        context.set_trailing_metadata(((STATUS_TRAILER, status.SerializeToString()),))
        await context.abort(grpc_code(status.code), details)


def unary(method: Callable[..., Awaitable[Reply]]) -> Callable[..., Awaitable[Reply]]:
    """A unary RPC whose errors end the call through :func:`status_on_error`."""
    @functools.wraps(method)
    async def rpc(self, request, context: grpc.aio.ServicerContext) -> Reply:
        async with status_on_error(context, self.engine.metrics):
            return await method(self, request, context)
    return rpc


# What each RPC needs (service/access/auth.py); tests/test_auth.py checks every RPC of the proto is here.
SCOPES = {"RenderStream": "render", "Render": "render", "ListAvatars": "render", "GetAvatar": "render",
          "LoadAvatar": "render", "UnloadAvatar": "avatars:write"}


class RenderService(pb_grpc.RenderServiceServicer):
    def __init__(self, engine: Engine):
        self.engine = engine

    async def caller(self, context: grpc.aio.ServicerContext, rpc: str) -> Principal:
        """The caller of an RPC, from ``authorization: Bearer <key>`` metadata: Unauthenticated, PermissionDenied
        without the RPC's scope (raised inside :func:`status_on_error`, they end the call with that code)."""
        metadata = {k.lower(): v for k, v in (context.invocation_metadata() or ()) if isinstance(v, str)}
        principal = await asyncio.to_thread(self.engine.access.authenticate, bearer(metadata.get("authorization")))
        return principal.require(SCOPES[rpc])

    async def RenderStream(self, request_iterator: AsyncIterator[pb.StreamRequest],
                           context: grpc.aio.ServicerContext) -> AsyncIterator[pb.StreamResponse]:
        requests = aiter(request_iterator)
        async with status_on_error(context, self.engine.metrics):
            principal = await self.caller(context, "RenderStream")
        try:
            first = await anext(requests)
        except StopAsyncIteration:
            return
        async with status_on_error(context, self.engine.metrics):
            if first.WhichOneof("msg") != "open":
                raise InvalidArgument("the first message must open a session", field="open")
            session = await self.engine.open(first.open, "grpc", principal)

        async def pump() -> None:
            try:
                async for request in requests:
                    session.handle(request)
                session.end_input()
            except (asyncio.CancelledError, grpc.RpcError):
                self.engine.close_session(session)

        reader = asyncio.create_task(pump())
        try:
            yield session.header()
            async for reply in session.responses():
                yield reply
                if reply.HasField("status") and reply.status.code != pb.OK:
                    context.set_code(grpc_code(reply.status.code))
                    context.set_details(reply.status.message)
        finally:
            reader.cancel()
            self.engine.close_session(session)

    @unary
    async def Render(self, request: pb.RenderRequest, context) -> pb.RenderResponse:
        return pb.RenderResponse(frame=await self.engine.render_once(request, await self.caller(context, "Render")))

    @unary
    async def ListAvatars(self, request: pb.ListAvatarsRequest, context) -> pb.ListAvatarsResponse:
        return pb.ListAvatarsResponse(avatars=self.engine.list_avatars(await self.caller(context, "ListAvatars")))

    @unary
    async def GetAvatar(self, request: pb.GetAvatarRequest, context) -> pb.AvatarInfo:
        return self.engine.avatar_info(request.id, await self.caller(context, "GetAvatar"))

    @unary
    async def LoadAvatar(self, request: pb.LoadAvatarRequest, context) -> pb.AvatarInfo:
        return await self.engine.load(request.id, await self.caller(context, "LoadAvatar"))

    @unary
    async def UnloadAvatar(self, request: pb.UnloadAvatarRequest, context) -> pb.AvatarInfo:
        return self.engine.unload(request.id, await self.caller(context, "UnloadAvatar"))


def connection_options(settings) -> list[tuple[str, int]]:
    """gRPC channel arguments from the deployment settings: max connection age (and its grace) and max idle, in
    milliseconds; a setting of 0 adds nothing (gRPC's default: no limit)."""
    age, idle = settings.grpc_max_connection_age_seconds, settings.grpc_max_connection_idle_seconds
    options = [("grpc.max_connection_idle_ms", idle)] if idle > 0 else []
    if age > 0:
        options += [("grpc.max_connection_age_ms", age),
                    ("grpc.max_connection_age_grace_ms", settings.grpc_max_connection_age_grace_seconds)]
    return [(name, max(1, round(seconds * 1000))) for name, seconds in options]


# Per connection: a client opening more streams at once waits for one to end (gRPC queues them client-side).
MAX_CONCURRENT_STREAMS = 100


def guard_options(settings, max_connections: int | None = None) -> list[tuple[str, int]]:
    """gRPC channel arguments that bound slow, idle and half-open clients (issue 28) without cutting long-lived
    render streams (they last up to ``max_stream_seconds``):

    - ``grpc.max_allowed_incoming_connections``: ``max_connections`` (the process's, fitted to its descriptor
      limit at start) open connections; past it new ones are closed at once. gRPC has no per-address limit.
    - ``grpc.server_handshake_timeout_ms``: ``header_timeout_seconds``: a connection that has not finished its
      handshake (TLS, the HTTP/2 preface and SETTINGS) by then is closed.
    - ``grpc.max_concurrent_streams``: :data:`MAX_CONCURRENT_STREAMS` streams at once per connection.
    - keepalive: the server pings every 20 s and closes a connection whose ping is not answered within 10 s, also
      on connections without a call (``keepalive_permit_without_calls``, which also lets clients ping those) and
      on streams that carry no data for minutes (``http2.max_pings_without_data`` 0: no cap on pings between data
      frames), so a half-open connection is gone within about 30 s; clients may ping every 5 s at most.
    Connections idle without calls close after ``grpc_max_connection_idle_seconds`` (:func:`connection_options`)."""
    connections = max_connections or settings.max_connections
    return [("grpc.max_allowed_incoming_connections", connections),
            ("grpc.server_handshake_timeout_ms", max(1, round(settings.header_timeout_seconds * 1000))),
            ("grpc.max_concurrent_streams", MAX_CONCURRENT_STREAMS),
            ("grpc.keepalive_time_ms", 20_000),
            ("grpc.keepalive_timeout_ms", 10_000),
            ("grpc.keepalive_permit_without_calls", 1),
            ("grpc.http2.max_pings_without_data", 0),
            ("grpc.http2.min_ping_interval_without_data_ms", 5_000)]


REFLECTION_V1 = "grpc.reflection.v1.ServerReflection"


def _reflection_v1(names) -> grpc.GenericRpcHandler:
    """Server reflection as ``grpc.reflection.v1`` beside grpcio-reflection's ``v1alpha`` (clients that speak only
    v1 fail otherwise). The two protocols' messages are the same on the wire (v1 is v1alpha renamed), so v1 calls
    are served by the v1alpha servicer."""
    servicer = reflection.aio.ReflectionServicer(names)
    handler = grpc.stream_stream_rpc_method_handler(
        servicer.ServerReflectionInfo,
        request_deserializer=reflection_pb2.ServerReflectionRequest.FromString,
        response_serializer=reflection_pb2.ServerReflectionResponse.SerializeToString)
    return grpc.method_handlers_generic_handler(REFLECTION_V1, {"ServerReflectionInfo": handler})


class GrpcServer:
    """The gRPC server of one process; ``port`` is the bound port (useful with port 0)."""

    def __init__(self, engine: Engine, host: str, port: int, *, max_connections: int | None = None):
        """``max_connections``: open connections at most (default: the ``max_connections`` setting)."""
        s = engine.settings
        self.server = grpc.aio.server(options=[
            ("grpc.max_receive_message_length", s.max_message_bytes),
            ("grpc.max_send_message_length", 64 << 20),
            *guard_options(s, max_connections),
            *connection_options(s),
        ])
        pb_grpc.add_RenderServiceServicer_to_server(RenderService(engine), self.server)
        self.health = health.aio.HealthServicer()
        health_pb2_grpc.add_HealthServicer_to_server(self.health, self.server)
        names = (SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME, REFLECTION_V1)
        reflection.enable_server_reflection(names, self.server)
        self.server.add_generic_rpc_handlers((_reflection_v1(names),))
        address = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        if s.tls_cert_file is not None:
            credentials = grpc.ssl_server_credentials([(s.tls_key_file.read_bytes(), s.tls_cert_file.read_bytes())])
            self.port = self.server.add_secure_port(address, credentials)
        else:
            self.port = self.server.add_insecure_port(address)

    async def start(self) -> None:
        await self.server.start()
        await self.set_serving(False)

    async def set_serving(self, serving: bool) -> None:
        status = health_pb2.HealthCheckResponse.SERVING if serving else health_pb2.HealthCheckResponse.NOT_SERVING
        for name in ("", SERVICE_NAME):
            await self.health.set(name, status)

    async def stop(self, grace: float) -> None:
        await self.server.stop(grace)
