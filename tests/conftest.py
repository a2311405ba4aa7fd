import contextlib
import functools
import secrets
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from render_core.tools.synth import synth_avatar


@pytest.fixture(scope="session")
def avatar():
    """A small synthetic avatar (600 face Gaussians, 6 blendshapes, SH degree 3, 75 mouth Gaussians)."""
    return synth_avatar(gaussians=600, blendshapes=6, seed=3)


@pytest.fixture(scope="session")
def tiny_video_archive(head, tmp_path_factory) -> bytes:
    """A tar.gz of a 12-frame 64 x 64 synthetic tracked video on the open head (10 training, 2 held-out frames),
    its dataset inside one top-level folder ``video``: what the job tests upload."""
    import io
    import tarfile

    from render_core.data.generate import synth_dataset

    folder = tmp_path_factory.mktemp("video") / "video"
    synth_dataset(folder, frames=12, size=64, seed=1, facemodel=head)
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        tar.add(folder, arcname="video")
    return buffer.getvalue()


@pytest.fixture(scope="session")
def head():
    """The open head face model (the one the package ships)."""
    from render_core.facemodel.open_head import open_head

    return open_head()


@pytest.fixture(autouse=True)
def _deterministic():
    torch.manual_seed(0)


class LiveServer:
    """A real service process's servers (gRPC + HTTP on loopback) running on an event loop in a thread.

    The transport tests run it with ``auth="off"`` (what they check is the same either way); tests/test_auth.py
    runs it with keys (``auth="keys"``): then ``api_key`` is the admin key it created and ``headers`` carry it."""

    def __init__(self, data_dir, **overrides):
        overrides.setdefault("auth", "off")
        import asyncio
        import threading

        from service.server import Service
        from service.settings import Settings

        defaults = {"demo_avatar": "synthetic", "demo_gaussians": 3000, "demo_blendshapes": 8, "warmup_size": 64}
        settings = Settings(data_dir=data_dir, host="127.0.0.1", grpc_port=0, http_port=0,
                            **{**defaults, **overrides})
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="live-server", daemon=True)
        self.thread.start()
        self.service = Service(settings)
        self.call(self.service.start(), timeout=120)
        self.engine = self.service.engine
        self.http_url = f"http://127.0.0.1:{self.service.http_port}"
        self.ws_url = f"ws://127.0.0.1:{self.service.http_port}/v1/stream"
        self.grpc_target = f"127.0.0.1:{self.service.grpc_port}"
        self.avatar_id = "demo"
        key_file = settings.data_dir / "admin.key"
        self.api_key = key_file.read_text().strip() if key_file.is_file() else None
        self.headers = {"Authorization": f"Bearer {self.api_key}"} if self.api_key else {}

    @functools.cached_property
    def keys(self):
        """The server's API key database (tests create and revoke keys through it)."""
        from service.access.keys import KeyStore

        return KeyStore(self.service.training.jobs.engine)

    def call(self, coro, timeout: float = 60):
        """Run a coroutine on the server's loop and wait for its result."""
        import asyncio

        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def stop(self) -> None:
        self.call(self.service.stop(), timeout=60)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)


@pytest.fixture(scope="session")
def live_server(tmp_path_factory):
    """The service on loopback with a small demo avatar ("demo": 3000 Gaussians, 8 blendshapes)."""
    server = LiveServer(tmp_path_factory.mktemp("live-server"))
    yield server
    server.stop()


# ------------------------------------------------------------------------------------------- Chromium
CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")


def chromium(profile: Path, *extra: str, window: str = "1280,1100") -> Iterator:
    """Headless Debian Chromium through ChromeDriver with its profile in ``profile`` and ``extra`` switches; skipped,
    with the install command, without them. Selenium is pointed at both binaries, so Selenium Manager never looks
    for a browser on the network."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists()]
    if missing:
        pytest.skip(f"{', '.join(missing)} missing: apt-get update && apt-get install -y chromium chromium-driver")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    # No background networking: this machine has no internet, and Chromium's own lookups only slow it down.
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", f"--window-size={window}", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync", "--disable-quic",
                f"--user-data-dir={profile}", *extra):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    drv = webdriver.Chrome(service=Service(executable_path=str(CHROMEDRIVER)), options=options)
    try:
        yield drv
    finally:
        drv.quit()


@pytest.fixture
def driver(tmp_path) -> Iterator:
    """The page tests' browser (:func:`chromium`); 1280 x 1100: the screenshots show the curves and the preview
    without scrolling."""
    yield from chromium(tmp_path / "chromium-profile")


# ------------------------------------------------------------------------------------------- PostgreSQL
PG_HOST, PG_PORT = "127.0.0.1", 5432


@pytest.fixture(scope="session")
def pg_admin_user():
    """The PostgreSQL user that can create databases (None and why, when there is no server)."""
    psycopg = pytest.importorskip("psycopg")
    errors = []
    for user in ("postgres", "root"):
        try:
            with psycopg.connect(host=PG_HOST, port=PG_PORT, dbname="test", user=user, connect_timeout=3):
                return user, None
        except psycopg.Error as exc:
            errors.append(f"{user}: {str(exc).strip().splitlines()[0]}")
    return None, "; ".join(errors)


@contextlib.contextmanager
def postgres_database(pg_admin_user, prefix: str = "blendsplat_test"):
    """The URL of a fresh PostgreSQL database of the test's own, dropped afterwards (the test skips, saying why,
    when PostgreSQL is unreachable)."""
    import psycopg

    user, why = pg_admin_user
    if user is None:
        pytest.skip(f"PostgreSQL at {PG_HOST}:{PG_PORT} is unreachable ({why})")
    name = f"{prefix}_{secrets.token_hex(6)}"
    with psycopg.connect(host=PG_HOST, port=PG_PORT, dbname="test", user=user, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    try:
        yield f"postgresql+psycopg://{user}@{PG_HOST}:{PG_PORT}/{name}"
    finally:
        with psycopg.connect(host=PG_HOST, port=PG_PORT, dbname="test", user=user, autocommit=True) as admin:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


@pytest.fixture
def coturn(tmp_path) -> Iterator[tuple[str, str]]:
    """coturn (Debian's turnserver) on 127.0.0.1 only, use-auth-secret, loopback peers allowed, relay ports in a
    small range: (its ``turn:`` URL, the shared secret); skipped without it (the WebRTC relay tests)."""
    import shutil
    import socket
    import subprocess
    import time

    binary = shutil.which("turnserver")
    if binary is None:
        pytest.skip("coturn is not installed: apt-get install -y coturn")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    low, secret = 49160 + port % 1000 * 10, "coturn-test-secret"
    log = tmp_path / "turnserver.log"
    process = subprocess.Popen(
        [binary, "-n", "--listening-ip=127.0.0.1", "--relay-ip=127.0.0.1", f"--listening-port={port}",
         f"--min-port={low}", f"--max-port={low + 9}", "--use-auth-secret", f"--static-auth-secret={secret}",
         "--realm=blendsplat", "--allow-loopback-peers", "--no-cli", "--no-tls", "--no-dtls", "--fingerprint",
         f"--pidfile={tmp_path / 'turnserver.pid'}", "--log-file=stdout", "--simple-log"],
        stdout=log.open("w"), stderr=subprocess.STDOUT)
    try:
        time.sleep(0.5)
        if process.poll() is not None:
            pytest.fail(f"turnserver exited: {log.read_text()[-2000:]}")
        yield f"turn:127.0.0.1:{port}?transport=udp", secret
    finally:
        process.terminate()
        try:
            process.wait(5)
        except subprocess.TimeoutExpired:
            process.kill()
