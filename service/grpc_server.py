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
from grpc_reflection.v1alpha import reflection

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc

from .engine import Engine
from .errors import InvalidArgument, grpc_code, to_status

log = logging.getLogger(__name__)
SERVICE_NAME = pb.DESCRIPTOR.services_by_name["RenderService"].full_name
Reply = TypeVar("Reply")


@contextlib.asynccontextmanager
async def status_on_error(context: grpc.aio.ServicerContext) -> AsyncIterator[None]:
    """End the call with the status of any error raised inside: its code from :func:`service.errors.to_status`,
    its details ``"field: message"`` (gRPC has no field slot). Errors that are not typed are INTERNAL, logged."""
    try:
        yield
    except grpc.aio.AbortError:
        raise  # already a status
    except Exception as exc:  # noqa: BLE001 - every failure becomes a status
        status = to_status(exc)
        if status.code == pb.INTERNAL:
            log.exception("internal error", exc_info=exc)
        details = f"{status.field}: {status.message}" if status.field else status.message
        await context.abort(grpc_code(status.code), details)


def unary(method: Callable[..., Awaitable[Reply]]) -> Callable[..., Awaitable[Reply]]:
    """A unary RPC whose errors end the call through :func:`status_on_error`."""
    @functools.wraps(method)
    async def rpc(self, request, context: grpc.aio.ServicerContext) -> Reply:
        async with status_on_error(context):
            return await method(self, request, context)
    return rpc


class RenderService(pb_grpc.RenderServiceServicer):
    def __init__(self, engine: Engine):
        self.engine = engine

    async def RenderStream(self, request_iterator: AsyncIterator[pb.StreamRequest],
                           context: grpc.aio.ServicerContext) -> AsyncIterator[pb.StreamResponse]:
        requests = aiter(request_iterator)
        try:
            first = await anext(requests)
        except StopAsyncIteration:
            return
        async with status_on_error(context):
            if first.WhichOneof("msg") != "open":
                raise InvalidArgument("the first message must open a session", field="open")
            session = await self.engine.open(first.open, "grpc")

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
        return pb.RenderResponse(frame=await self.engine.render_once(request))

    @unary
    async def ListAvatars(self, request: pb.ListAvatarsRequest, context) -> pb.ListAvatarsResponse:
        return pb.ListAvatarsResponse(avatars=self.engine.list_avatars())

    @unary
    async def GetAvatar(self, request: pb.GetAvatarRequest, context) -> pb.AvatarInfo:
        return self.engine.avatar_info(request.id)

    @unary
    async def LoadAvatar(self, request: pb.LoadAvatarRequest, context) -> pb.AvatarInfo:
        return await self.engine.load(request.id)

    @unary
    async def UnloadAvatar(self, request: pb.UnloadAvatarRequest, context) -> pb.AvatarInfo:
        return self.engine.unload(request.id)


def connection_options(settings) -> list[tuple[str, int]]:
    """gRPC channel arguments from the deployment settings: max connection age (and its grace) and max idle, in
    milliseconds; a setting of 0 adds nothing (gRPC's default: no limit)."""
    age, idle = settings.grpc_max_connection_age_seconds, settings.grpc_max_connection_idle_seconds
    options = [("grpc.max_connection_idle_ms", idle)] if idle > 0 else []
    if age > 0:
        options += [("grpc.max_connection_age_ms", age),
                    ("grpc.max_connection_age_grace_ms", settings.grpc_max_connection_age_grace_seconds)]
    return [(name, max(1, round(seconds * 1000))) for name, seconds in options]


class GrpcServer:
    """The gRPC server of one process; ``port`` is the bound port (useful with port 0)."""

    def __init__(self, engine: Engine, host: str, port: int):
        s = engine.settings
        self.server = grpc.aio.server(options=[
            ("grpc.max_receive_message_length", s.max_message_bytes),
            ("grpc.max_send_message_length", 64 << 20),
            ("grpc.keepalive_time_ms", 20_000),
            ("grpc.keepalive_timeout_ms", 10_000),
            ("grpc.http2.min_ping_interval_without_data_ms", 5_000),
            *connection_options(s),
        ])
        pb_grpc.add_RenderServiceServicer_to_server(RenderService(engine), self.server)
        self.health = health.aio.HealthServicer()
        health_pb2_grpc.add_HealthServicer_to_server(self.health, self.server)
        reflection.enable_server_reflection((SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME),
                                            self.server)
        address = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
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
