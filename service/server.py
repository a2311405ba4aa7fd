"""One service process: the engine, the gRPC server and the HTTP server on one event loop, with graceful drain.

Start-up: settings are validated, the bundle store is created (with a demo avatar when it is empty) and cleared of
the temporary files a killed process left, both servers listen, then one warm-up frame is rendered; only then do
/readyz and gRPC health report ready. An avatar the warm-up cannot load (too large for the cache, broken) is
logged and the built-in one warms up instead; a warm-up that fails altogether leaves the process up and not
ready, the reason in the log and in /readyz's body - it never exits the process.
SIGTERM/SIGINT: not ready at once and new streams are refused; after ``shutdown_delay_seconds`` request bodies
still arriving (uploads) are refused with 503, open streams get no new frames, frames already received are sent,
every stream ends with an UNAVAILABLE status (a WebRTC session's on its data channel, then every peer connection
closes), then both servers stop - all within ``drain_seconds`` (uvicorn's and gRPC's own grace periods are what is
left of it).

Training jobs: the process opens the job database (migrated to head) and the upload folder at start, serves the
jobs' REST routes (:mod:`service.jobs.api`; submitting and reading jobs needs no worker in this process), and runs
the retention sweep at start and every ``RETENTION_INTERVAL_SECONDS``. :func:`up` adds one worker child process
(``blendsplat up``: the whole single-machine product).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import os
import signal
import sys
import time
from pathlib import Path

import uvicorn

from render_core.errors import BlendsplatError

from .access.auth import Access
from .access.keys import KeyStore
from .demo import DEMO_ID, DEMO_OWNER, make_demo_avatar
from .engine import Engine
from .errors import ServiceError
from .grpc_server import GrpcServer
from .http.app import create_app, stop_reading_bodies
from .http.connections import ConnectionGuard, protocols
from .jobs.events import close_streams
from .jobs.training import RETENTION_INTERVAL_SECONDS, Training, open_stores
from .jobs.webhooks import WebhookDispatcher, load_secret
from .metrics import Metrics
from .settings import Settings
from .store import BundleStore

log = logging.getLogger(__name__)
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


def open_urls(host: str, http_port: int, grpc_port: int, *, tls: bool = False) -> dict[str, str]:
    """The addresses to open on this machine for a server listening on ``host``: the pages ``demo``, ``docs`` and
    ``jobs`` (https with TLS) and the gRPC target ``grpc``. A wildcard host (0.0.0.0, ::) is reached as
    127.0.0.1."""
    shown = "127.0.0.1" if host in ("", "0.0.0.0", "::", "[::]") else host
    if ":" in shown and not shown.startswith("["):
        shown = f"[{shown}]"  # an IPv6 address in a URL
    base = f"{'https' if tls else 'http'}://{shown}:{http_port}"
    return {"demo": f"{base}/demo", "docs": f"{base}/docs", "jobs": f"{base}/jobs", "grpc": f"{shown}:{grpc_port}"}


class _Uvicorn(uvicorn.Server):
    """uvicorn without its own signal handling: this process drains first, then stops it."""

    def capture_signals(self):  # noqa: D102
        import contextlib

        return contextlib.nullcontext()


class Service:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.metrics = Metrics()
        self.engine: Engine | None = None  # built complete at start: its access needs the job database
        self.grpc: GrpcServer | None = None
        self.http: _Uvicorn | None = None
        self.app = None  # the HTTP app (its state carries readiness reasons and the drain's body refusal)
        self.connections: ConnectionGuard | None = None  # the HTTP server's connection counts and timers
        self.training: Training | None = None
        self.webhooks: WebhookDispatcher | None = None  # sends job webhooks (service/jobs/webhooks.py)
        self._retention: asyncio.Task | None = None
        self._sweep: asyncio.Future | None = None  # the sweep in its thread (cancelling the task does not stop it)
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
        s = self.settings
        jobs, uploads = await asyncio.to_thread(open_stores, s)  # the job database (migrated) and the upload folder
        store = BundleStore(s.bundle_dir)
        access = Access(s, KeyStore(jobs.engine), on_limit_failure=self.metrics.limit_failures.inc,
                        usage=[store.tenant_bytes, uploads.tenant_bytes, jobs.tenant_work_bytes],
                        files=uploads.tenant_files)  # bytes on disk, from what was recorded when written
        self.training = Training(s, jobs, uploads, access=access, writable=store.writable,
                                 metrics=self.metrics)
        self.engine = engine = Engine(s, self.metrics, access=access, store=store)
        await asyncio.to_thread(access.bootstrap)
        self.webhooks = WebhookDispatcher(s, self.training.jobs, await asyncio.to_thread(load_secret, s))
        self.webhooks.start()
        await engine.start()
        stale = engine.store.clean_stale(older_than=2 * s.body_timeout_seconds)
        if stale:
            log.info("removed %d temporary file(s) a stopped process left in the bundle store", len(stale))
        if s.demo_avatar != "none" and not engine.store.ids():
            t0 = time.perf_counter()
            what = await asyncio.to_thread(make_demo_avatar, s, engine)
            log.info("created the demo avatar %r (%s) in %.2f s", DEMO_ID, what, time.perf_counter() - t0)
        elif DEMO_ID in engine.store.ids() and not engine.store.sidecars(DEMO_ID)[1].exists():
            engine.store.set_owner(DEMO_ID, DEMO_OWNER)  # a demo made before avatars had owners: public
        # slow and half-open clients: head and body timeouts, connections per server and per address (issue 28)
        self.connections = ConnectionGuard.from_settings(s)
        self.grpc = GrpcServer(engine, s.host, s.grpc_port, max_connections=self.connections.max_connections)
        await self.grpc.start()
        self.app = create_app(engine, self.training)
        self.app.state.problems["bundle_store"] = engine.store.problem  # /readyz says why the store is not usable
        http_protocol, ws_protocol = protocols(self.connections)
        # timeout_graceful_shutdown: replaced by what is left of the drain time when stopping (stop)
        config = uvicorn.Config(self.app, host=s.host, port=s.http_port, log_level="warning", http=http_protocol,
                                ws=ws_protocol, ws_max_size=s.max_message_bytes, lifespan="off",
                                timeout_graceful_shutdown=5, ssl_certfile=s.tls_cert_file, ssl_keyfile=s.tls_key_file)
        self.http = _Uvicorn(config)
        self._http_task = asyncio.create_task(self.http.serve())
        while not self.http.started:
            if self._http_task.done():
                await self._http_task  # re-raises why it could not start (e.g. the port is taken)
                raise RuntimeError("the HTTP server stopped during start-up")
            await asyncio.sleep(0.02)
        warmed = await self._warm_up()
        gc.freeze()  # start-up objects (torch, the avatars) never become garbage: keep the collector off them
        self._retention = asyncio.create_task(self._sweep_periodically(), name="retention")
        if warmed:
            await self.grpc.set_serving(True)
            log.info("ready: gRPC on port %d, HTTP on port %d", self.grpc_port, self.http_port)
            urls = open_urls(s.host, self.http_port, self.grpc_port, tls=s.tls_cert_file is not None)
            log.info("open %s (drive the demo avatar), %s (the API), %s (training jobs); gRPC streams: %s%s",
                     urls["demo"], urls["docs"], urls["jobs"], urls["grpc"],
                     "" if s.host in LOCAL_HOSTS else f" (listening on {s.host})")

    async def _warm_up(self) -> bool:
        """One warm-up frame: of the demo avatar (else the store's first), else of the built-in avatar when that
        one cannot be loaded (too large for the cache, a broken bundle: logged, served as errors to its clients).
        A failure of the warm-up itself leaves the process up and not ready, the reason in the log and in
        /readyz's body; whether it is ready."""
        engine, t0 = self.engine, time.perf_counter()
        try:
            ids = engine.store.ids()
            chosen = DEMO_ID if DEMO_ID in ids else (ids[0] if ids else None)
            try:
                await engine.warm_up(chosen)
            except (ServiceError, BlendsplatError) as e:
                if chosen is None:
                    raise
                log.warning("warm-up: avatar %r cannot be loaded (%s); warming up with the built-in avatar",
                            chosen, e)
                await engine.warm_up(None)
        except Exception as e:  # noqa: BLE001 - never exit: stay up, not ready, and say why
            reason = f"the warm-up frame failed: {type(e).__name__}: {str(e)[:500]}"
            self.app.state.problems["warm_up"] = reason
            log.error("not ready: %s", reason, exc_info=e)
            return False
        log.info("warm-up frame rendered in %.1f s", time.perf_counter() - t0)
        return True

    async def _sweep_periodically(self) -> None:
        """Retention (uploads, work folders, leftovers): at start, then every RETENTION_INTERVAL_SECONDS."""
        while True:
            self._sweep = asyncio.ensure_future(asyncio.to_thread(self.training.sweep))
            try:
                await asyncio.shield(self._sweep)
            except asyncio.CancelledError:
                raise
            except Exception:  # noqa: BLE001 - a failed sweep (database away) is retried next time
                log.warning("retention sweep failed; retrying in %.0f s", RETENTION_INTERVAL_SECONDS, exc_info=True)
            await asyncio.sleep(RETENTION_INTERVAL_SECONDS)

    async def stop(self) -> None:
        """Drain, then stop both servers (idempotent)."""
        if self._stopping:
            return await self.stopped.wait()
        self._stopping = True
        s = self.settings
        if self._retention is not None:
            self._retention.cancel()
        # the dispatcher stops beside the drain: an attempt in flight gets a second, else is retried later
        webhooks_stopped = asyncio.ensure_future(self.webhooks.stop()) if self.webhooks is not None else None
        engine = self.engine
        if engine is not None:
            engine.begin_drain()
        if self.grpc:
            await self.grpc.set_serving(False)
        deadline = time.monotonic() + s.shutdown_delay_seconds + s.drain_seconds
        if s.shutdown_delay_seconds:
            log.info("not ready; open streams go on for %.1f s", s.shutdown_delay_seconds)
            await asyncio.sleep(s.shutdown_delay_seconds)
        log.info("draining (up to %.1f s)", s.drain_seconds)
        if self.app is not None:
            stop_reading_bodies(self.app)  # uploads still arriving: 503, their temp files removed
            close_streams(self.app)  # job event streams end now (clients reconnect with Last-Event-ID)
        # The streams get the drain time but a slice kept for the servers to close their connections.
        if engine is not None:
            await engine.drain(max(0.0, deadline - time.monotonic() - min(1.0, s.drain_seconds / 4)))
        await asyncio.sleep(0.05)  # let the final statuses go out

        def left() -> float:  # never 0: uvicorn reads 0 as "wait for ever"
            return max(0.1, deadline - time.monotonic())

        if self.app is not None:  # WebRTC peers: their final statuses leave, then every peer connection closes
            await self.app.state.webrtc.drain(left())
        if self.grpc:
            await self.grpc.stop(grace=min(1.0, left()))
        if self.http:
            self.http.config.timeout_graceful_shutdown = left()
            self.http.should_exit = True
            await self._http_task
        if engine is not None:
            await engine.close()
        if self._sweep is not None:
            with contextlib.suppress(Exception):
                await self._sweep  # a sweep in progress finishes before its stores close
        if webhooks_stopped is not None:
            await webhooks_stopped
        if self.training is not None:
            await asyncio.to_thread(self.training.close)
        if engine is not None:
            await asyncio.to_thread(engine.access.close)  # gives back this replica's stream leases at once
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


# ------------------------------------------------------------------------------------------- blendsplat up
WORKER_NICE = 10  # the worker runs at a lower CPU priority than the render service it shares the machine with
WORKER_STOP_SECONDS = 120.0  # SIGTERM: how long the worker may take to checkpoint and hand its job back
_RESTART_DELAYS = (1.0, 2.0, 5.0, 10.0, 30.0)  # after an unexpected exit (reset once it ran a minute)
# The child: niced, and sent SIGTERM by the kernel if this process dies without forwarding it (Linux).
_CHILD = ("import ctypes, os, signal, sys\n"
          "os.nice({nice})\n"
          "try:\n"
          "    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG\n"
          "except (OSError, AttributeError):\n"
          "    pass\n"
          "if os.getppid() != {parent}:\n"
          "    sys.exit(0)  # the parent is already gone\n"
          "from service.cli import main\n"
          "sys.exit(main(sys.argv[1:]))\n")


class WorkerProcess:
    """One ``blendsplat worker`` child process: niced by :data:`WORKER_NICE`, stdout and stderr inherited,
    restarted (with a growing delay) when it exits while this process is not stopping; :meth:`stop` sends SIGTERM
    (the worker checkpoints its job and hands it back) and waits, then kills it after :data:`WORKER_STOP_SECONDS`."""

    def __init__(self, argv: list[str], *, nice: int = WORKER_NICE, stop_seconds: float = WORKER_STOP_SECONDS):
        self.argv = argv
        self.nice = nice
        self.stop_seconds = stop_seconds
        self.process: asyncio.subprocess.Process | None = None
        self.starts = 0
        self._stopping = False
        self._task: asyncio.Task | None = None

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process else None

    def start(self) -> None:
        self._task = asyncio.create_task(self._supervise(), name="worker-supervisor")

    async def _spawn(self) -> None:
        code = _CHILD.format(nice=int(self.nice), parent=os.getpid())
        self.process = await asyncio.create_subprocess_exec(sys.executable, "-c", code, *self.argv,
                                                            cwd=str(Path.cwd()))
        self.starts += 1
        log.info("worker started (pid %d, nice +%d)", self.process.pid, self.nice)

    async def _supervise(self) -> None:
        failures = 0
        while not self._stopping:
            await self._spawn()
            began = time.monotonic()
            code = await self.process.wait()
            if self._stopping:
                return
            if time.monotonic() - began > 60:
                failures = 0
            delay = _RESTART_DELAYS[min(failures, len(_RESTART_DELAYS) - 1)]
            failures += 1
            log.warning("the worker (pid %d) exited unexpectedly with %s; restarting in %.0f s", self.process.pid,
                        code, delay)
            await asyncio.sleep(delay)

    async def stop(self) -> int | None:
        """SIGTERM the worker and wait for it (kill it after ``stop_seconds``); its exit code."""
        self._stopping = True
        process = self.process
        if self._task is not None and (process is None or process.returncode is not None):
            self._task.cancel()  # sleeping before a restart, or not started yet
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            process = self.process
        if process is None or process.returncode is not None:
            return process.returncode if process else None
        with contextlib.suppress(ProcessLookupError):
            process.send_signal(signal.SIGTERM)
        try:
            code = await asyncio.wait_for(process.wait(), self.stop_seconds)
        except TimeoutError:
            log.warning("the worker did not stop within %.0f s: killing it (its job's lease expires and the job is "
                        "requeued)", self.stop_seconds)
            with contextlib.suppress(ProcessLookupError):
                process.kill()
            code = await process.wait()
        if self._task is not None:
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        log.info("worker stopped (exit code %s)", code)
        return code


def worker_argv(settings: Settings, metrics_port: int = 0, device: str = "cpu") -> list[str]:
    """The ``blendsplat worker`` command line for the same data dir and job database as ``settings``."""
    argv = ["worker", "--data-dir", str(Path(settings.data_dir).absolute()), "--jobs-url",
            settings.jobs_database_url, "--device", device]
    if metrics_port:
        argv += ["--metrics-port", str(metrics_port)]
    return argv


async def up(settings: Settings, *, worker_metrics_port: int = 0, device: str = "cpu") -> None:
    """``blendsplat up``: :func:`serve` in this process plus one worker child process on the same data dir and job
    database. The service starts first (it migrates the job database), then the worker. SIGTERM or SIGINT: both
    stop at once, the service drains its streams and the worker hands its job back; returns when both ended."""
    sys.setswitchinterval(0.001)
    service = Service(settings)
    worker = WorkerProcess(worker_argv(settings, worker_metrics_port, device))
    stopping: list[asyncio.Task] = []

    def shut_down() -> None:
        if not stopping:
            stopping.append(asyncio.ensure_future(asyncio.gather(service.stop(), worker.stop())))

    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, shut_down)
    try:
        await service.start()
        worker.start()
        await service.stopped.wait()
    finally:
        shut_down()
        await stopping[0]
