"""The gRPC transport (grpc.aio): blendsplat.v1.RenderService, grpc.health.v1 and server reflection.

A thin adapter: every call goes to the :class:`~service.engine.Engine`; errors become status codes through
:func:`service.errors.to_status` (INVALID_ARGUMENT naming the field, NOT_FOUND, RESOURCE_EXHAUSTED, UNAVAILABLE).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc

from .engine import Engine
from .errors import grpc_code, to_status

log = logging.getLogger(__name__)
SERVICE_NAME = pb.DESCRIPTOR.services_by_name["RenderService"].full_name


async def _abort(context: grpc.aio.ServicerContext, exc: BaseException) -> None:
    status = to_status(exc)
    if status.code == pb.INTERNAL:
        log.exception("internal error", exc_info=exc)
    details = f"{status.field}: {status.message}" if status.field else status.message  # no field slot in gRPC
    await context.abort(grpc_code(status.code), details)


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
        if first.WhichOneof("msg") != "open":
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "open: the first message must open a session")
        try:
            session = await self.engine.open(first.open, "grpc")
        except Exception as e:  # noqa: BLE001 - mapped to a status code
            await _abort(context, e)

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

    async def Render(self, request: pb.RenderRequest, context: grpc.aio.ServicerContext) -> pb.RenderResponse:
        try:
            return pb.RenderResponse(frame=await self.engine.render_once(request))
        except Exception as e:  # noqa: BLE001
            await _abort(context, e)

    async def ListAvatars(self, request, context) -> pb.ListAvatarsResponse:
        return pb.ListAvatarsResponse(avatars=self.engine.list_avatars())

    async def GetAvatar(self, request: pb.GetAvatarRequest, context) -> pb.AvatarInfo:
        try:
            return self.engine.avatar_info(request.id)
        except Exception as e:  # noqa: BLE001
            await _abort(context, e)

    async def LoadAvatar(self, request: pb.LoadAvatarRequest, context) -> pb.AvatarInfo:
        try:
            await self.engine.cache.load(request.id)
            return self.engine.avatar_info(request.id)
        except Exception as e:  # noqa: BLE001
            await _abort(context, e)

    async def UnloadAvatar(self, request: pb.UnloadAvatarRequest, context) -> pb.AvatarInfo:
        try:
            info = self.engine.avatar_info(request.id)
            self.engine.cache.unload(request.id)
            info.loaded, info.memory_bytes = False, 0
            return info
        except Exception as e:  # noqa: BLE001
            await _abort(context, e)


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
