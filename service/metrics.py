"""Prometheus metrics of one service process (a registry per engine, so test servers do not share counters).

The training jobs' side (issue 15): queue depth by state is read from the job database when ``/metrics`` is
scraped (:meth:`Metrics.watch_jobs`: one grouped count per scrape, so every API replica reports the same numbers);
uploads, submissions and retention deletions are counted where they happen. Per-attempt durations, attempts lost
or handed back, heartbeats and iterations per second are the worker's own metrics (``service/jobs/worker.py``, served
on its ``--metrics-port``): the worker is the one that sees them.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, ProcessCollector
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector

if TYPE_CHECKING:
    from .jobs import JobStore

log = logging.getLogger(__name__)

STAGES = ("queue", "blend", "lbs", "raster", "encode", "total")  # the per-frame stages (StageTimings' *_ms fields)
# Milliseconds-scale frame stages, in seconds.
_BUCKETS = (0.001, 0.002, 0.004, 0.008, 0.012, 0.016, 0.024, 0.033, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1.0, 2.5)


class Metrics:
    def __init__(self) -> None:
        r = self.registry = CollectorRegistry()
        ProcessCollector(registry=r)  # process_resident_memory_bytes, CPU seconds, open fds
        self.frames = Counter("blendsplat_frames", "frames rendered and sent", ["codec"], registry=r)
        self.frame_bytes = Counter("blendsplat_frame_bytes", "encoded frame bytes sent", ["codec"], registry=r)
        self.dropped = Counter("blendsplat_dropped_frames", "poses replaced by newer ones before rendering",
                               registry=r)
        self.errors = Counter("blendsplat_errors", "errors answered, by status code and transport (grpc, websocket, "
                              "http): failed opens and calls, in-stream errors, HTTP 4xx and 5xx",
                              ["code", "transport"], registry=r)
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
        self.limit_failures = Counter("blendsplat_limit_checks_failed", "per-key limit checks that could not reach "
                                      "Redis (let through: limits fail open)", registry=r)
        self.ready = Gauge("blendsplat_ready", "1 when the process takes new streams", registry=r)
        self.webrtc_sessions = Gauge("blendsplat_webrtc_sessions", "open WebRTC sessions (peer connections, each "
                                     "with its engine session)", registry=r)
        self.webrtc_closed = Counter("blendsplat_webrtc_closed", "WebRTC sessions closed, by why (deleted, ended, "
                                     "failed, timeout, vanished, drain)", ["reason"], registry=r)
        for stage in STAGES:
            self.stage.labels(stage)
        # Training jobs: uploads and submissions seen by this process, retention deletions.
        self.uploads = Counter("blendsplat_dataset_uploads", "dataset uploads by result (accepted, or the refusal: "
                               "too_large, archive, dataset)", ["result"], registry=r)
        self.upload_bytes = Counter("blendsplat_dataset_upload_bytes", "bytes of accepted dataset archives",
                                    registry=r)
        self.jobs_submitted = Counter("blendsplat_jobs_submitted", "training jobs submitted (created, or replayed "
                                      "for a repeated Idempotency-Key)", ["result"], registry=r)
        self.retention_deleted = Counter("blendsplat_retention_deleted", "uploads and work folders deleted by the "
                                         "retention sweep", ["kind"], registry=r)
        for result in ("accepted", "too_large", "archive", "dataset"):
            self.uploads.labels(result)
        for result in ("created", "replayed"):
            self.jobs_submitted.labels(result)
        for kind in ("upload", "work_folder"):
            self.retention_deleted.labels(kind)
        self._jobs_collector: _JobsCollector | None = None

    def watch_jobs(self, store: JobStore) -> None:
        """Report the queue depth by state from ``store`` at every scrape (``blendsplat_jobs{state}``) and whether
        the job database answered (``blendsplat_jobs_database_up``)."""
        if self._jobs_collector is None:
            self._jobs_collector = _JobsCollector(store)
            self.registry.register(self._jobs_collector)
        else:
            self._jobs_collector.store = store


class _JobsCollector(Collector):
    """Reads ``counts_by_state()`` when scraped (a grouped count: cheap on both job databases)."""

    def __init__(self, store: JobStore) -> None:
        self.store = store

    def describe(self) -> Iterator[GaugeMetricFamily]:
        yield GaugeMetricFamily("blendsplat_jobs", "training jobs in the job database, by state", labels=["state"])
        yield GaugeMetricFamily("blendsplat_jobs_database_up", "1 when the job database answered the scrape")

    def collect(self) -> Iterator[GaugeMetricFamily]:
        up = GaugeMetricFamily("blendsplat_jobs_database_up", "1 when the job database answered the scrape")
        try:
            counts = self.store.counts_by_state()
        except Exception as exc:  # noqa: BLE001 - a scrape must not fail because the database is away
            log.warning("metrics: the job database did not answer (%s)", exc)
            up.add_metric([], 0)
            yield up
            return
        jobs = GaugeMetricFamily("blendsplat_jobs", "training jobs in the job database, by state", labels=["state"])
        for state, count in counts.items():
            jobs.add_metric([state.value], count)
        up.add_metric([], 1)
        yield jobs
        yield up
