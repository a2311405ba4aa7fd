"""One service process: the engine, the gRPC server and the HTTP server on one event loop, with graceful drain.

Start-up: settings are validated, the bundle store is created (with a demo avatar when it is empty), both servers
listen, then one warm-up frame is rendered; only then do /readyz and gRPC health report ready.
SIGTERM/SIGINT: not ready at once and new streams are refused; after ``shutdown_delay_seconds`` open streams get
no new frames, frames already received are sent, every stream
ends with an UNAVAILABLE status, then both servers stop - all within ``drain_seconds``.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import signal
import sys
import time

import uvicorn

from render_core.bundle import write_bundle
from render_core.errors import FaceModelError
from render_core.facemodel.open_head import open_head
from render_core.tools.synth import synth_avatar
from render_core.train.initialize import demo_albedo, init_avatar

from .engine import Engine
from .grpc_server import GrpcServer
from .http_app import create_app
from .settings import Settings

log = logging.getLogger(__name__)
DEMO_ID = "demo"


def make_demo_avatar(settings: Settings, engine: Engine) -> str:
    """The demo avatar ``demo``: ``demo_gaussians`` Gaussians (15/16 face, 1/16 mouth) in fp16, initialised on the
    open head model (K = 52 ARKit expressions, shipped with the package), or, when the settings ask for it, a
    synthetic avatar of the same size whose blendshapes have compact support."""
    n = settings.demo_gaussians
    try:
        if settings.demo_avatar == "synthetic":
            raise FaceModelError("the settings ask for a synthetic demo avatar")
        model = open_head()
    except FaceModelError as e:
        log.warning("demo avatar: synthetic (%s)", e)
        avatar = synth_avatar(gaussians=n - n // 8, mouth=n // 8, blendshapes=settings.demo_blendshapes, seed=0,
                              local=True)
    else:
        avatar = init_avatar(model, gaussians=n - n // 16, mouth=n // 16, opacity=0.95, albedo=demo_albedo(model))
    write_bundle(avatar, engine.store.path(DEMO_ID), precision="fp16")
    engine.store.adopt(DEMO_ID)  # verified once, here: later loads trust the store's record
    return avatar.face_model


class _Uvicorn(uvicorn.Server):
    """uvicorn without its own signal handling: this process drains first, then stops it."""

    def capture_signals(self):  # noqa: D102
        import contextlib

        return contextlib.nullcontext()


class Service:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.engine = Engine(settings)
        self.grpc: GrpcServer | None = None
        self.http: _Uvicorn | None = None
        self.stopped = asyncio.Event()
        self._stopping = False

    @property
    def grpc_port(self) -> int:
        return self.grpc.port if self.grpc else 0

    @property
    def http_port(self) -> int:
        if not self.http or not self.http.servers:
            return 0
        return self.http.servers[0].sockets[0].getsockname()[1]

    async def start(self) -> None:
        s, engine = self.settings, self.engine
        await engine.start()
        if s.demo_avatar != "none" and not engine.store.ids():
            t0 = time.perf_counter()
            face_model = await asyncio.to_thread(make_demo_avatar, s, engine)
            log.info("created the demo avatar %r (%d Gaussians, %s) in %.1f s", DEMO_ID, s.demo_gaussians,
                     face_model, time.perf_counter() - t0)
        self.grpc = GrpcServer(engine, s.host, s.grpc_port)
        await self.grpc.start()
        config = uvicorn.Config(create_app(engine), host=s.host, port=s.http_port, log_level="warning",
                                ws_max_size=s.max_message_bytes, lifespan="off", timeout_graceful_shutdown=5)
        self.http = _Uvicorn(config)
        self._http_task = asyncio.create_task(self.http.serve())
        while not self.http.started:
            if self._http_task.done():
                await self._http_task  # re-raises why it could not start (e.g. the port is taken)
                raise RuntimeError("the HTTP server stopped during start-up")
            await asyncio.sleep(0.02)
        ids = engine.store.ids()
        t0 = time.perf_counter()
        await engine.warm_up(DEMO_ID if DEMO_ID in ids else (ids[0] if ids else None))
        log.info("warm-up frame rendered in %.1f s", time.perf_counter() - t0)
        gc.freeze()  # start-up objects (torch, the avatars) never become garbage: keep the collector off them
        await self.grpc.set_serving(True)
        log.info("ready: gRPC on port %d, HTTP on port %d", self.grpc_port, self.http_port)

    async def stop(self) -> None:
        """Drain, then stop both servers (idempotent)."""
        if self._stopping:
            return await self.stopped.wait()
        self._stopping = True
        s = self.settings
        self.engine.begin_drain()
        if self.grpc:
            await self.grpc.set_serving(False)
        if s.shutdown_delay_seconds:
            log.info("not ready; open streams go on for %.1f s", s.shutdown_delay_seconds)
            await asyncio.sleep(s.shutdown_delay_seconds)
        log.info("draining (up to %.1f s)", s.drain_seconds)
        await self.engine.drain(self.settings.drain_seconds)
        await asyncio.sleep(0.05)  # let the final statuses go out
        if self.grpc:
            await self.grpc.stop(grace=1.0)
        if self.http:
            self.http.should_exit = True
            await self._http_task
        await self.engine.close()
        self.stopped.set()
        log.info("stopped")


async def serve(settings: Settings) -> None:
    # The render thread retakes the GIL after every native call; a shorter switch interval keeps it from waiting
    # up to 5 ms behind the event loop's message parsing.
    sys.setswitchinterval(0.001)
    service = Service(settings)
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, lambda: asyncio.ensure_future(service.stop()))
    await service.start()
    await service.stopped.wait()
