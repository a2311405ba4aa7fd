"""The one settings object of every service process: environment variables prefixed ``BLENDSPLAT_``.

Defaults run on one machine with no external service (a local folder as the bundle store). Every value is
validated at start-up, so a bad deployment fails fast with the variable named.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

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
    encode_threads: int = Field(
        2, ge=0, le=64, description="threads that encode rendered frames (JPEG, PNG, H.264) off the render thread, "
                                    "which goes on with the next batch meanwhile; a batch's frames encode in "
                                    "parallel, each stream's one at a time and in order. 0: on the render thread, "
                                    "after each batch's render")
    raster_lazy_tiles: bool = Field(True, description="native compositing: a tile's splats gathered 64 at a time "
                                                      "and the tile stopped once every pixel has (same pixels)")
    raster_square_blocks: bool = Field(True, description="native compositing in 4x4-pixel blocks instead of 8x2 "
                                                         "(same pixels)")
    raster_direct_rgba8: bool = Field(True, description="native: 8-bit RGBA for the encoders written by the "
                                                        "compositing loop, not converted from float images after it "
                                                        "(same pixels)")
    raster_eight_bit_stop: bool = Field(True, description="native, 8-bit output: a pixel stops compositing once "
                                                          "what lies behind it could move it by at most a quarter "
                                                          "of a level (within one level of the exact image, "
                                                          "fewer splats composited)")
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
    max_extraction_ratio: float = Field(
        50.0, ge=1, description="an archive whose extraction would take more than this many bytes on disk per "
                                "archive byte (each file rounded up to whole 4 KiB blocks) is refused at upload "
                                "(422, reason bomb); honest datasets of PNG frames are near 1. Not applied below "
                                "16 MiB extracted, nor to a video job's own tracked frames")
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
    # decoding, past these; the job's tracker applies the same ones (render_core/tracking/video.py, VideoLimits).
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
    token_secret: str | None = Field(
        None, description="the HMAC key of session tokens (POST /v1/tokens); replicas must share one. Unset: "
                          "generated on first use into <data_dir>/token.secret (mode 0600)")
    token_max_seconds: int = Field(3600, ge=1, le=86400, description="the longest a session token may live "
                                                                     "(POST /v1/tokens, expires_in)")
    key_uploads_per_hour: int = Field(20, ge=1, description="uploads (datasets and bundles) per non-admin key per "
                                                            "hour")
    key_jobs_per_hour: int = Field(20, ge=1, description="training jobs submitted per non-admin key per hour")
    tenant_storage_bytes: int = Field(
        20 << 30, ge=1 << 20, description="storage quota of a tenant: bytes on disk of its bundles, its uploads as "
                                          "extracted and its jobs' work folders (checkpoints, tracked frames, "
                                          "overlays); over it an upload or job submission is refused (429) and a "
                                          "running job fails (StorageQuotaExceeded)")
    tenant_max_files: int = Field(
        200_000, ge=1, description="files and folders a tenant's uploads may hold on disk, all together (more: the "
                                   "upload is refused, 429, and nothing is kept)")

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

    # WebRTC egress (service/webrtc/, the signalling in service/http/webrtc.py).
    webrtc_host_addresses: Annotated[list[str], NoDecode] = Field(
        [], description="the only local addresses WebRTC gathers host candidates on and offers in its answers "
                        "(comma list of IP addresses, e.g. 127.0.0.1 on a test machine, or the address clients "
                        "reach the pod at); empty: every interface's, as aioice gathers them (it skips 127.0.0.1). "
                        "When every address is loopback, remote candidates that are not loopback are ignored")
    webrtc_stun_urls: Annotated[list[str], NoDecode] = Field(
        [], description="STUN servers (comma list of stun:HOST[:PORT]): the server asks the first for its "
                        "server-reflexive candidate, and clients get them all as Link rel=ice-server headers")
    webrtc_turn_urls: Annotated[list[str], NoDecode] = Field(
        [], description="TURN servers for clients (comma list of turn:HOST[:PORT][?transport=udp|tcp] or turns:...), "
                        "sent as Link rel=ice-server headers with short-lived credentials from webrtc_turn_secret")
    webrtc_turn_secret: str | None = Field(
        None, description="the TURN server's shared secret (coturn: use-auth-secret, static-auth-secret): each "
                          "session's username is EXPIRY:blendsplat, its credential base64(HMAC-SHA1(secret, "
                          "username)); needed with webrtc_turn_urls")
    webrtc_turn_ttl_seconds: float = Field(3600.0, gt=0, le=86400 * 7, description="TURN credentials' lifetime")
    webrtc_max_offer_bytes: int = Field(32768, ge=1024, le=1 << 20, description="largest SDP offer (POST "
                                                                                "/v1/webrtc; more: 413)")
    webrtc_connect_seconds: float = Field(
        15.0, gt=0, le=300, description="a WebRTC session whose peer has not connected (ICE and DTLS) this long "
                                        "after the offer is closed and freed")
    webrtc_peer_timeout_seconds: float = Field(
        10.0, gt=0, le=300, description="a connected WebRTC session that hears nothing from its peer (RTCP reports, "
                                        "data-channel messages) this long is closed and freed (a vanished peer)")
    webrtc_max_bitrate: int = Field(
        800_000, ge=250_000, le=20_000_000, description="the most bits per second a WebRTC video encoder is set "
                                                          "to, whatever the receiver's bandwidth estimate (REMB) "
                                                          "allows")

    @field_validator("webrtc_host_addresses", "webrtc_stun_urls", "webrtc_turn_urls", mode="before")
    @classmethod
    def _comma_list(cls, value: object) -> object:
        if isinstance(value, str):
            return [part.strip() for part in value.split(",") if part.strip()]
        return value

    @field_validator("webrtc_host_addresses")
    @classmethod
    def _ip_addresses(cls, value: list[str]) -> list[str]:
        import ipaddress

        for address in value:
            try:
                ipaddress.ip_address(address)
            except ValueError:
                raise ValueError(f"{address!r} is not an IP address (a comma list of them)") from None
        return value

    @field_validator("webrtc_stun_urls", "webrtc_turn_urls")
    @classmethod
    def _ice_urls(cls, value: list[str], info) -> list[str]:
        schemes = ("stun:", "stuns:") if info.field_name == "webrtc_stun_urls" else ("turn:", "turns:")
        for url in value:
            if not url.startswith(schemes) or len(url) > 500 or any(c in url for c in ' <>,;"'):
                raise ValueError(f"{url[:100]!r} is not a {' or '.join(schemes)} URL")
        return value

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
        if self.webrtc_turn_urls and not self.webrtc_turn_secret:
            raise ValueError("webrtc_turn_urls needs webrtc_turn_secret (the TURN server's shared secret)")
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
