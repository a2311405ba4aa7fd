"""One claimed job while it trains (:class:`Attempt`: heartbeats, the per-iteration cancel and lease check) and the
worker's metrics. The worker's contract is :mod:`service.jobs.worker`'s docstring; this is the part of it that two
threads share: the training thread reports progress and asks :meth:`Attempt.should_stop` before every iteration,
a heartbeat thread extends the lease every ``settings.heartbeat_seconds`` and carries the latest progress.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError

from render_core.train.trainer import Progress

from .models import Job, JobRecord, JobState

if TYPE_CHECKING:
    from .worker import Worker

log = logging.getLogger("service.jobs.worker")  # the worker's log (the same name when it runs as __main__)

MAX_ERROR_CHARS = 2000
_JOB_BUCKETS = (1, 5, 10, 30, 60, 120, 300, 600, 1200, 1800, 3600, 7200, 14400, 28800, 86400)


def error_text(exc: BaseException) -> str:
    """``<type>: <message>``, at most :data:`MAX_ERROR_CHARS` characters (what a failed job records)."""
    text = f"{type(exc).__name__}: {exc}"
    return text if len(text) <= MAX_ERROR_CHARS else text[: MAX_ERROR_CHARS - 3] + "..."


# ------------------------------------------------------------------------------------------------------ metrics
class WorkerMetrics:
    """The worker's Prometheus metrics, in their own registry (never the global one)."""

    def __init__(self, registry: CollectorRegistry | None = None) -> None:
        r = self.registry = registry if registry is not None else CollectorRegistry()
        self.heartbeats = Counter("blendsplat_worker_heartbeats", "heartbeats sent, by result (ok, lost, error)",
                                  ["result"], registry=r)
        self.iterations_per_second = Gauge("blendsplat_worker_iterations_per_second",
                                           "training iterations per second over the last heartbeat interval "
                                           "(0 when idle)", registry=r)
        self.jobs_finished = Counter("blendsplat_worker_jobs_finished", "job attempts ended by this worker, by "
                                     "state (succeeded, failed, cancelled, released, lost)", ["state"], registry=r)
        self.job_seconds = Histogram("blendsplat_worker_job_seconds", "wall time of a job attempt, claim to end",
                                     ["state"], buckets=_JOB_BUCKETS, registry=r)
        for result in ("ok", "lost", "error"):
            self.heartbeats.labels(result)

# ------------------------------------------------------------------------------------------------- one attempt
class LeaseLost(Exception):
    """Raised out of the Trainer's cancel check when the job is no longer ours: :meth:`Trainer.run` then ends
    without its final checkpoint, so a worker that lost its lease writes nothing more to a work folder that
    another worker may own by now."""


class Attempt:
    """One claimed job while it trains: what the training thread and the heartbeat thread share."""

    def __init__(self, worker: Worker, job: Job, stop: threading.Event):
        self.worker, self.job, self.stop = worker, job, stop
        self.lost = threading.Event()  # the lease is gone (swept, finished elsewhere, deleted): touch nothing
        self.cancel = threading.Event()  # a cancel was requested
        self.done = threading.Event()  # heartbeats stop
        self._lock = threading.Lock()
        self._progress: dict[str, Any] | None = None
        self._sent: int | None = None  # the iteration of the last progress sent
        self._rate_mark: tuple[float, int] | None = None  # (monotonic time, iteration) at the previous heartbeat
        self._warned = 0.0
        self._beat_lock = threading.Lock()  # one heartbeat at a time (the thread's, or the training thread's last)
        self.checkpoint: Path | None = None  # the checkpoint last recorded on the row
        self._thread = threading.Thread(target=self._beat_loop, name=f"heartbeat-{job.id}", daemon=True)

    # ---- progress (training thread) ----
    def record(self, event: Progress) -> None:
        loss = event.losses.get("loss")
        report = {
            "iteration": event.iteration, "total_iterations": event.total,
            "fraction": event.iteration / event.total if event.total else 1.0,
            "eta_seconds": event.eta, "loss": loss if loss is None or math.isfinite(loss) else None,
            "psnr": event.psnr if math.isfinite(event.psnr) else None, "gaussians": event.gaussians,
        }
        with self._lock:
            self._progress = report

    def _pending(self) -> dict[str, Any] | None:
        with self._lock:
            if self._progress is None or self._progress["iteration"] == self._sent:
                return None
            return dict(self._progress)

    # ---- heartbeats (background thread) ----
    def start(self) -> None:
        self._thread.start()

    def finish_heartbeats(self) -> None:
        self.done.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()

    def _beat_loop(self) -> None:
        interval = self.worker.settings.heartbeat_seconds
        while not self.done.wait(interval):
            self.beat()
            self.worker._maybe_sweep()

    def beat(self) -> None:
        """One heartbeat: extend the lease, send the progress if it changed, note a lost lease or a cancel."""
        with self._beat_lock:
            self._beat()

    def _beat(self) -> None:
        w, job = self.worker, self.job
        progress = self._pending()
        try:
            reply = w.store.heartbeat(job.id, w.worker_id, w.settings.job_lease_seconds, progress=progress)
        except (SQLAlchemyError, OSError) as exc:
            w.metrics.heartbeats.labels("error").inc()
            log.warning("job %s: heartbeat failed (%s); retrying at the next interval", job.id, error_text(exc))
            return
        if progress is not None:
            with self._lock:
                self._sent = progress["iteration"]
            now = time.monotonic()
            if self._rate_mark is not None and now > self._rate_mark[0]:
                done = progress["iteration"] - self._rate_mark[1]
                w.metrics.iterations_per_second.set(max(done, 0) / (now - self._rate_mark[0]))
            self._rate_mark = (now, progress["iteration"])
        if not reply.owned:
            w.metrics.heartbeats.labels("lost").inc()
            if not self.lost.is_set() and not self.done.is_set():
                log.warning("job %s: the lease is lost (swept, finished elsewhere or deleted); stopping", job.id)
            self.lost.set()
            return
        w.metrics.heartbeats.labels("ok").inc()
        if reply.cancel_requested:
            self.cancel.set()

    # ---- the per-iteration check (training thread) ----
    def control(self) -> tuple[bool, bool]:
        """(owned, cancel_requested) from the job's row now: one primary-key query. (True, False) when the
        database does not answer (a transient error must not stop training; the lease decides)."""
        w = self.worker
        try:
            with w.store.engine.connect() as connection:
                row = connection.execute(
                    select(JobRecord.state, JobRecord.lease_owner, JobRecord.cancel_requested)
                    .where(JobRecord.id == self.job.id)).first()
        except (SQLAlchemyError, OSError) as exc:
            now = time.monotonic()
            if now - self._warned > 10:
                log.warning("job %s: cannot read the cancel flag (%s)", self.job.id, error_text(exc))
                self._warned = now
            return True, False
        if row is None:
            return False, False
        owned = row.state == JobState.RUNNING.value and row.lease_owner == w.worker_id
        return owned, bool(row.cancel_requested)

    def should_stop(self) -> bool:
        """The Trainer's ``should_cancel``, asked before every iteration: True on shutdown or a cancel (noted by a
        heartbeat, or read from the row now); :class:`LeaseLost` when the job is no longer ours."""
        if self.lost.is_set():
            raise LeaseLost(self.job.id)
        if self.stop.is_set() or self.cancel.is_set():
            return True
        owned, cancel = self.control()
        if not owned:
            self.lost.set()
            raise LeaseLost(self.job.id)
        if cancel:
            self.cancel.set()
            return True
        return False

    def refresh(self) -> None:
        """Read the row once more (before a commit or a hand-back) and note a lost lease or a cancel."""
        owned, cancel = self.control()
        if not owned:
            self.lost.set()
        if cancel:
            self.cancel.set()
