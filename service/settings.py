"""The one settings object of every service process: environment variables prefixed ``BLENDSPLAT_``.

Defaults run on one machine with no external service (a local folder as the bundle store). Every value is
validated at start-up, so a bad deployment fails fast with the variable named.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

# Every form of API key the service accepts (service/access/keys.py): printable ASCII without spaces, 16 to 512
# characters. Its own keys (bsk_<id>_<secret>) are of this form; so must an admin key made elsewhere be.
API_KEY_PATTERN = re.compile(r"^[!-~]{16,512}$")


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="BLENDSPLAT_", extra="ignore")

    data_dir: Path = Field(Path("data"), description="root of the bundle store (bundles/) and caches")
    host: str = Field("127.0.0.1", description="interface both servers listen on (default: this machine only; "
                                               "0.0.0.0 for every interface, as the container images set)")
    grpc_port: int = Field(50051, ge=0, le=65535, description="0 picks a free port")
    http_port: int = Field(8080, ge=0, le=65535, description="0 picks a free port")

    backend: str | None = Field(None, description="rasterizer backend (default: native where built)")
    render_threads: int = Field(0, ge=0, description="native render threads (0: all cores)")
    cache_bytes: int = Field(4 << 30, ge=1 << 20, description="memory budget of loaded avatars")
    max_sessions: int = Field(32, ge=1, description="concurrent streams per process; more get RESOURCE_EXHAUSTED")
    max_in_flight: int = Field(2, ge=1, le=16, description="default frames sent but not acknowledged")
    max_size: int = Field(2048, ge=16, le=8192, description="largest output width or height")
    max_batch: int = Field(8, ge=1, le=64, description="frames of one avatar rendered in one call")
    max_frame_splat_pixels: float = Field(
        1e10, gt=0, description="per-frame render budget: a frame whose estimated (Gaussian, pixel) pairs (the "
                                "avatar at rest, its camera and size) pass it is refused (RESOURCE_EXHAUSTED naming "
                                "the size or camera); a batch holds at most this much work")
    max_message_bytes: int = Field(1 << 20, ge=1024, description="largest request message (gRPC, WebSocket)")
    max_upload_bytes: int = Field(2 << 30, ge=1024, description="largest bundle upload")
    body_timeout_seconds: float = Field(
        30.0, gt=0, description="an HTTP request body (an upload) that sends no bytes this long is refused (408) "
                                "and what it had written is removed; the connection of a body that no route reads "
                                "is closed a little later (service/http/connections.py)")
    header_timeout_seconds: float = Field(
        10.0, gt=0, le=300, description="an HTTP request's head (request line and headers) must arrive within this "
                                        "long of the connection opening or of the previous answer, else the "
                                        "connection is closed (408 when part of it came); also the gRPC server's "
                                        "handshake timeout. Streams, once open, are never cut by it")
    max_connections: int = Field(
        1000, ge=1, description="open connections per server (HTTP and gRPC, each); past it a new connection is "
                                "closed at once (HTTP: 503 with Retry-After). Lowered at start to a third of the "
                                "process's file-descriptor limit, so slow clients cannot use every descriptor")
    max_connections_per_address: int = Field(
        64, ge=1, description="open HTTP connections from one client address; past it that address's new "
                              "connections are closed at once (503 with Retry-After). Behind a proxy that does not "
                              "keep client addresses, raise it to max_connections")
    shutdown_delay_seconds: float = Field(
        0.0, ge=0, description="SIGTERM: keep serving open streams (not ready, no new ones) this long before "
                               "draining, so load balancers stop routing here first")
    drain_seconds: float = Field(10.0, ge=0, description="SIGTERM: time to finish frames in flight before exit")

    demo_avatar: Literal["trained", "open-head", "synthetic", "none"] = Field(
        "trained", description="the avatar put in an empty bundle store on start: trained (the package's demo "
                               "avatar, trained by `blendsplat bundle build-demo` on the open head's synthetic "
                               "video; copied in well under a second), open-head (initialised on the open head "
                               "model, untrained), synthetic, or none")
    demo_gaussians: int = Field(64_000, ge=16, description="open-head and synthetic demo avatars' size (face + mouth "
                                                           "Gaussians; the trained one has its own)")
    demo_blendshapes: int = Field(52, ge=1, description="synthetic demo avatar only (the open head has 52)")
    warmup_size: int = Field(512, ge=16, description="readiness waits for one frame of this size")
    adapter_budget_ms: float = Field(
        20.0, gt=0, description="per-frame adapter budget: a retargeting adapter's run (the frames of one render "
                                "call) that takes more CPU time than this is refused (RESOURCE_EXHAUSTED naming "
                                "the adapter) and those frames are not rendered; the adapter is logged once")

    # Training jobs (the job database, dataset uploads, workers).
    jobs_url: str | None = Field(
        None, description="job database URL: sqlite:///PATH (one machine) or postgresql+psycopg://... (default: "
                          "a SQLite file <data_dir>/jobs.db)")
    max_dataset_bytes: int = Field(8 << 30, ge=1024, description="largest dataset archive upload")
    upload_retention_hours: float = Field(
        168.0, ge=0, description="uploaded datasets (face video: biometric data) are deleted this long after "
                                 "upload (0: never by age; DELETE /v1/uploads/{id} deletes at once)")
    work_retention_hours: float = Field(
        168.0, ge=0, description="a finished job's work folder (checkpoints, previews, log) is deleted this long "
                                 "after it ended (0: never by age)")
    job_lease_seconds: float = Field(60.0, ge=1, description="a worker that misses heartbeats this long loses "
                                                             "its job to the next worker")
    heartbeat_seconds: float = Field(5.0, gt=0, description="worker heartbeat and progress interval")
    job_max_attempts: int = Field(3, ge=1, le=100, description="attempts of a job before it fails")
    # Video uploads (service/jobs/video.py): refused at upload from the container's metadata and packets, before
    # decoding, past these; each is at most the tracker's own limit (render_core/tracking/video.py, VideoLimits).
    max_video_seconds: float = Field(300.0, gt=0, description="longest video upload, in seconds")
    max_video_side: int = Field(4096, ge=16, description="largest long side (pixels) of a video upload")
    max_video_frames: int = Field(9000, ge=1, description="most frames of a video upload")

    # Access: API keys, tenants, TLS, browsers (service/access/auth.py).
    auth: Literal["keys", "off"] = Field(
        "keys", description="keys: every API route and RPC needs an API key (health, metrics and the API docs stay "
                            "open); off: no authentication, for a trusted network only (a warning at start)")
    admin_key: str | None = Field(
        None, description="an admin API key to accept (e.g. from a Kubernetes Secret); its hash is recorded in the "
                          "key table at start. With no key at all, serve and up create one in <data_dir>/admin.key")
    tls_cert_file: Path | None = Field(None, description="PEM certificate chain: both servers speak TLS only")
    tls_key_file: Path | None = Field(None, description="PEM private key of tls_cert_file")
    allowed_origins: list[str] = Field(
        [], description="browser origins (scheme://host[:port]) allowed for CORS and WebSocket; the server's own "
                        "pages are always allowed")
    key_max_sessions: int = Field(8, ge=1, description="concurrent streams (render and job events) per non-admin "
                                                       "key (more: 429 / RESOURCE_EXHAUSTED); per replica unless "
                                                       "redis_url is set")
    key_max_renders: int = Field(4, ge=1, description="single-frame renders (POST /v1/render, the Render RPC) in "
                                                      "flight per non-admin key (more: 429 / RESOURCE_EXHAUSTED); per "
                                                      "replica unless redis_url is set")
    redis_url: str | None = Field(
        None, description="Redis (redis://[:password@]host:6379/0, rediss:// for TLS) holding the per-key limits, "
                          "so every replica counts against the same ones; unset: each replica counts its own")
    stream_key_check_seconds: float = Field(
        5.0, gt=0, le=60, description="how often an open stream (gRPC, WebSocket, job events) checks its key again "
                                      "in the key database: a revoked key's streams end within about this long "
                                      "(UNAUTHENTICATED)")
    max_stream_seconds: float = Field(
        3600.0, gt=0, description="a render stream (gRPC, WebSocket) ends after this long with UNAVAILABLE (the "
                                  "client opens a new one); job event streams have events_max_seconds")
    key_uploads_per_hour: int = Field(20, ge=1, description="uploads (datasets and bundles) per non-admin key per "
                                                            "hour")
    key_jobs_per_hour: int = Field(20, ge=1, description="training jobs submitted per non-admin key per hour")
    tenant_storage_bytes: int = Field(20 << 30, ge=1 << 20, description="storage quota of a tenant (its bundles "
                                                                        "and uploads)")

    # Job events and webhooks (service/jobs/events.py, service/jobs/webhooks.py).
    events_max_streams: int = Field(100, ge=1, description="concurrent job event streams (GET /v1/jobs/{id}/events) "
                                                           "per process; more get 429")
    events_max_seconds: float = Field(3600.0, gt=0, description="an event stream ends after this long (the client "
                                                                "reconnects with Last-Event-ID)")
    events_poll_seconds: float = Field(0.5, gt=0, description="how often an event stream looks for new events")
    events_keepalive_seconds: float = Field(15.0, gt=0, description="a comment line on an idle event stream this "
                                                                    "often (keeps proxies from closing it)")
    webhook_secret: str | None = Field(
        None, description="the HMAC-SHA256 key of webhook signatures ('whsec_' + base64, as in Standard Webhooks, "
                          "or any other text, used as UTF-8 bytes). Unset: generated at first start into "
                          "<data_dir>/webhook.secret (mode 0600); replicas must share it")
    webhook_timeout_seconds: float = Field(10.0, gt=0, description="one webhook attempt's HTTP timeout")
    webhook_max_attempts: int = Field(15, ge=1, le=100, description="attempts of a webhook before it is failed")
    webhook_retry_seconds: float = Field(86400.0, gt=0, description="no webhook attempt starts later than this "
                                                                    "after the state change; then it is failed")
    webhook_backoff_seconds: float = Field(5.0, gt=0, description="delay before the first retry; doubled on each "
                                                                  "one (with jitter)")
    webhook_backoff_max_seconds: float = Field(3600.0, gt=0, description="the longest delay between retries")
    webhook_poll_seconds: float = Field(1.0, gt=0, description="how often the dispatcher looks for due webhooks")
    webhook_private_networks: bool = Field(
        False, description="allow webhooks to hosts that resolve to loopback, private, link-local or other "
                           "non-public addresses (off: such a delivery fails at once, so a job cannot make the "
                           "service call into its own network)")

    # Deployment: gRPC connections of long-lived streams (service/grpc_server.py), so replicas rebalance.
    grpc_max_connection_age_seconds: float = Field(
        0.0, ge=0, description="the gRPC server ends a connection this long after it opened (GOAWAY; clients "
                               "reconnect, through the load balancer, to any replica), so long-lived streams "
                               "spread over new replicas; 0: never")
    grpc_max_connection_age_grace_seconds: float = Field(
        30.0, ge=0, description="after max connection age, the streams still open get this long to end before the "
                                "connection closes (a client then reopens its stream)")
    grpc_max_connection_idle_seconds: float = Field(
        0.0, ge=0, description="a gRPC connection with no call this long is closed; 0: never")

    @field_validator("admin_key")
    @classmethod
    def _admin_key(cls, value: str | None) -> str | None:
        if value is not None and not API_KEY_PATTERN.match(value):
            raise ValueError("an admin key is bsk_<10 hex>_<43 URL-safe base64 characters> (`blendsplat keys create`) "
                             "or 16 to 512 printable characters without spaces (e.g. `openssl rand -hex 32`)")
        return value

    @model_validator(mode="after")
    def _tls_pair(self) -> Settings:
        if (self.tls_cert_file is None) != (self.tls_key_file is None):
            raise ValueError("tls_cert_file and tls_key_file go together: set both (TLS) or neither")
        for name in ("tls_cert_file", "tls_key_file"):
            path = getattr(self, name)
            if path is not None and not path.is_file():
                raise ValueError(f"{name}: {path} is not a readable file")
        return self

    @property
    def bundle_dir(self) -> Path:
        return self.data_dir / "bundles"

    @property
    def upload_dir(self) -> Path:
        return self.data_dir / "uploads"

    @property
    def work_dir(self) -> Path:
        """Training work folders, one per job (``<work_dir>/<job id>``)."""
        return self.data_dir / "work"

    @property
    def facemodel_dir(self) -> Path:
        """Face models other than the shipped open head (e.g. FLAME), by name: ``<facemodel_dir>/<name>.*``."""
        return self.data_dir / "facemodels"

    @property
    def jobs_database_url(self) -> str:
        return self.jobs_url or f"sqlite:///{(self.data_dir / 'jobs.db').absolute()}"
