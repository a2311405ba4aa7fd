"""Prometheus metrics of one service process (a registry per engine, so test servers do not share counters)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, ProcessCollector

STAGES = ("queue", "blend", "lbs", "raster", "encode", "total")
# Milliseconds-scale frame stages, in seconds.
_BUCKETS = (0.001, 0.002, 0.004, 0.008, 0.012, 0.016, 0.024, 0.033, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1.0, 2.5)


class Metrics:
    def __init__(self) -> None:
        r = self.registry = CollectorRegistry()
        ProcessCollector(registry=r)  # process_resident_memory_bytes, CPU seconds, open fds
        self.frames = Counter("blendsplat_frames", "frames rendered and sent", ["codec"], registry=r)
        self.bytes_out = Counter("blendsplat_bytes_out", "encoded frame bytes sent", ["codec"], registry=r)
        self.dropped = Counter("blendsplat_dropped_frames", "poses replaced by newer ones before rendering",
                               registry=r)
        self.errors = Counter("blendsplat_errors", "requests rejected, by status code", ["code"], registry=r)
        self.stage = Histogram("blendsplat_stage_seconds", "time per frame and stage", ["stage"], buckets=_BUCKETS,
                               registry=r)
        self.batch = Histogram("blendsplat_batch_frames", "frames rendered per native call",
                               buckets=(1, 2, 3, 4, 6, 8, 12, 16, 32, 64), registry=r)
        self.sessions = Gauge("blendsplat_active_sessions", "open streams", ["transport"], registry=r)
        self.sessions_total = Counter("blendsplat_sessions", "streams opened", ["transport"], registry=r)
        self.cache_hits = Counter("blendsplat_avatar_cache_hits", "avatar lookups served from memory", registry=r)
        self.cache_misses = Counter("blendsplat_avatar_cache_misses", "avatar lookups that loaded a bundle",
                                    registry=r)
        self.cache_bytes = Gauge("blendsplat_avatar_cache_bytes", "memory held by loaded avatars", registry=r)
        self.cache_avatars = Gauge("blendsplat_avatar_cache_avatars", "loaded avatars", registry=r)
        self.ready = Gauge("blendsplat_ready", "1 when the process takes new streams", registry=r)
        for stage in STAGES:
            self.stage.labels(stage)
