import pytest
import torch

from render_core.tools.synth import synth_avatar


@pytest.fixture(scope="session")
def avatar():
    """A small synthetic avatar (600 face Gaussians, 6 blendshapes, SH degree 3, 75 mouth Gaussians)."""
    return synth_avatar(gaussians=600, blendshapes=6, seed=3)


@pytest.fixture(scope="session")
def head():
    """The open head face model (the one the package ships)."""
    from render_core.facemodel.open_head import open_head

    return open_head()


@pytest.fixture(autouse=True)
def _deterministic():
    torch.manual_seed(0)


class LiveServer:
    """A real service process's servers (gRPC + HTTP on loopback) running on an event loop in a thread."""

    def __init__(self, data_dir, **overrides):
        import asyncio
        import threading

        from service.server import Service
        from service.settings import Settings

        settings = Settings(data_dir=data_dir, host="127.0.0.1", grpc_port=0, http_port=0, demo_avatar="synthetic",
                            demo_gaussians=3000,
                            demo_blendshapes=8, warmup_size=64, **overrides)
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
