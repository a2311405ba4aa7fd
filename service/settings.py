"""The one settings object of every service process: environment variables prefixed ``BLENDSPLAT_``.

Defaults run on one machine with no external service (a local folder as the bundle store). Every value is
validated at start-up, so a bad deployment fails fast with the variable named.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="BLENDSPLAT_", extra="ignore")

    data_dir: Path = Field(Path("data"), description="root of the bundle store (bundles/) and caches")
    host: str = Field("0.0.0.0", description="interface both servers listen on")
    grpc_port: int = Field(50051, ge=0, le=65535, description="0 picks a free port")
    http_port: int = Field(8080, ge=0, le=65535, description="0 picks a free port")

    backend: str | None = Field(None, description="rasterizer backend (default: native where built)")
    render_threads: int = Field(0, ge=0, description="native render threads (0: all cores)")
    cache_bytes: int = Field(4 << 30, ge=1 << 20, description="memory budget of loaded avatars")
    max_sessions: int = Field(32, ge=1, description="concurrent streams per process; more get RESOURCE_EXHAUSTED")
    max_in_flight: int = Field(2, ge=1, le=16, description="default frames sent but not acknowledged")
    max_size: int = Field(2048, ge=16, le=8192, description="largest output width or height")
    max_batch: int = Field(8, ge=1, le=64, description="frames of one avatar rendered in one call")
    max_message_bytes: int = Field(1 << 20, ge=1024, description="largest request message (gRPC, WebSocket)")
    max_upload_bytes: int = Field(2 << 30, ge=1024, description="largest bundle upload")
    shutdown_delay_seconds: float = Field(
        0.0, ge=0, description="SIGTERM: keep serving open streams (not ready, no new ones) this long before "
                               "draining, so load balancers stop routing here first")
    drain_seconds: float = Field(10.0, ge=0, description="SIGTERM: time to finish frames in flight before exit")

    demo_avatar: Literal["open-head", "synthetic", "none"] = Field(
        "open-head", description="the avatar put in an empty bundle store on start: initialised on the open head "
                                 "model shipped with the package, synthetic, or none")
    demo_gaussians: int = Field(64_000, ge=16, description="demo avatar size (face + mouth Gaussians)")
    demo_blendshapes: int = Field(52, ge=1, description="synthetic demo avatar only (the open head has 52)")
    warmup_size: int = Field(512, ge=16, description="readiness waits for one frame of this size")

    @property
    def bundle_dir(self) -> Path:
        return self.data_dir / "bundles"
