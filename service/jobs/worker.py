"""The training worker (``blendsplat worker``): claims jobs from the job store and drives the :class:`Trainer`.

One process trains one job at a time (one GPU per worker in production). The job table is the only record of a
job (:mod:`service.jobs.store` states its contract); this module is its consumer::

    loop:  sweep() every lease/2 seconds (expired leases: requeued or failed)
           claim() the oldest queued job, else wait_for_work() (PostgreSQL LISTEN, SQLite short polling)
    job:   spec -> dataset folder of the upload, face model, Trainer (resumed from the work folder's checkpoint
           when there is one or the job is on a later attempt) -> Trainer.run() -> Trainer.finish() -> the bundle
           committed to the bundle store under the spec's avatar id -> finish(succeeded, result)

**The job spec** (JSON, the job row's ``spec``) is :class:`~service.jobs.schemas.JobSpec`, the one the REST side
validated the request with; the worker validates it again (:meth:`JobSpec.parse`: a bad value fails the job naming
the key, ``spec.<key>``; keys it does not know are ignored and logged). ``resolution`` (the longest image side)
trains on the dataset resampled to it (:mod:`service.jobs.resize`, written once into the work folder), and a
``log`` event says at which size it trains. The optional ``checkpoint_every`` (iterations between checkpoints,
default the preset's; previews follow it) and ``gaussians`` / ``mouth`` (initial face / mouth-interior Gaussians,
default the preset's) override the preset for a fresh start; a resumed job keeps its checkpoint's preset.

**A job from a video upload** runs one stage more, first: the video is tracked into a dataset in the work folder
(:mod:`service.jobs.track`: ``tracked/``, the ``overlay.png`` of the fitted points, the ``dataset.tar.gz`` archive,
and ``track.json`` last, which marks the stage complete, so a later attempt does not track again), with ``progress``
events of ``stage: "track"``; then it trains on that dataset like any other (open head). A tracking error (no face,
a corrupt stream, ...) fails the job with the tracker's named error.

**The work folder** ``<settings.work_dir>/<job id>/`` is the Trainer's workdir plus the worker's files
(:mod:`service.jobs.artefacts`): ``preview.png`` is replaced atomically every ``preview_every`` iterations (default
every checkpoint) and once more at the end of a finished training; ``avatar.bundle`` is the trained bundle (a copy
of it is what enters the bundle store). The REST side serves these files as the job's artefacts.

**What a running job records**

- heartbeats every ``settings.heartbeat_seconds`` (a background thread) extend the lease by
  ``settings.job_lease_seconds`` and carry the latest progress when it changed: ``iteration``,
  ``total_iterations``, ``fraction``, ``eta_seconds``, ``loss``, ``psnr``, ``gaussians`` (throttled to the heartbeat
  interval, not every step; one more report when training ends);
- ``set_checkpoint(<work folder>/checkpoints/ckpt_<iteration>.pt)`` after each checkpoint;
- a ``preview`` event ``{"iteration": i, "path": "preview.png"}`` after each preview;
- the work folder's bytes on disk (the row's ``work_bytes``, the tenant's storage quota counts them) at each
  checkpoint, at the end of each stage and of the attempt; past the tenant's quota the job fails with
  ``StorageQuotaExceeded`` (:mod:`service.jobs.quota`);
- ``log`` events: ``{"resumed_from": iteration, ...}`` when it resumed, the training size, and the reason
  when an attempt ends without finishing the job.

**How a job ends**

- trained: the bundle is committed (:meth:`service.store.BundleStore.commit`: validated, published atomically,
  recorded as verified) under ``spec["avatar_id"]``, then ``finish("succeeded", result={"avatar_id", "digest",
  "evaluation": {"psnr", "ssim", "psnr_head" when present} or null without held-out frames, "final_psnr",
  "iterations", "seconds"})`` (``seconds``: training seconds, earlier attempts included);
- any exception (a training error, a bad spec, the upload deleted, a face model missing, ...):
  ``finish("failed", error="<type>: <message>")``, at most 2000 characters;
- cancel: ``should_cancel`` is evaluated before every iteration (the Trainer's boundary) and reads the job's row
  (one primary-key query), so a cancel request that reached the database stops training before the next
  iteration; the Trainer checkpoints and the job ends ``cancelled`` (the checkpoint is kept). A cancel seen after
  training but before the commit also ends it cancelled, with nothing committed;
- lease lost (a heartbeat or the per-iteration query finds the job swept to another worker, finished or deleted):
  training stops before the next iteration without a final checkpoint (the folder may be another worker's by
  now), nothing is committed and the row is not touched;
- shutdown (the ``stop`` event: SIGTERM or SIGINT under :func:`main`): training stops at the next iteration
  boundary, the Trainer checkpoints and the job is handed back with ``release()`` (queued again with its
  checkpoint, the attempt not counted). A shutdown during the final export lets it complete (it is bounded).

**Resume**: a job claimed on a later attempt (``attempts > 1``) or whose work folder holds a checkpoint resumes
with :meth:`Trainer.resume` from the last checkpoint; the Trainer promises the same parameters as an
uninterrupted run.

**Face model**: the open head ships with the install (the Trainer's default). A dataset tracked with another
model (e.g. FLAME) needs ``<settings.facemodel_dir>/<face_model name>.*`` (a face-model file, e.g. made by
``blendsplat facemodel import-flame``); a missing one fails the job with an error naming the folder.

**Metrics** (its own CollectorRegistry, served by :func:`main` on ``--metrics-port``):
``blendsplat_worker_heartbeats_total{result=ok|lost|error}``, ``blendsplat_worker_iterations_per_second``,
``blendsplat_worker_jobs_finished_total{state}`` and ``blendsplat_worker_job_seconds{state}`` (an attempt's wall
time from claim to end), where ``state`` is ``succeeded``, ``failed``, ``cancelled``, ``released`` (handed back
on shutdown) or ``lost`` (the lease was taken away).
"""


from __future__ import annotations

import argparse
import logging
import os
import secrets
import signal
import socket
import threading
import time
from pathlib import Path
from typing import Any

from sqlalchemy.exc import SQLAlchemyError

from render_core.train.trainer import raster_step

from ..db import redacted
from ..errors import NotFound, hide_paths
from ..settings import Settings
from ..store import BundleStore
from .attempt import Attempt, LeaseLost, WorkerMetrics, error_text
from .models import Job, JobState
from .run import JobRun
from .store import JobStore
from .uploads import UploadStore

__all__ = ["Worker", "WorkerMetrics", "add_arguments", "default_worker_id", "main"]

log = logging.getLogger("service.jobs.worker")  # the same name when run as __main__

IDLE_WAIT_SECONDS = 1.0  # longest single wait for work: how soon an idle worker notices ``stop``
DB_RETRY_SECONDS = 2.0  # back-off after the job database failed in the loop


def default_worker_id() -> str:
    """``<hostname>-<pid>-<random>``: unique per process, readable in the job table."""
    return f"{socket.gethostname()}-{os.getpid()}-{secrets.token_hex(3)}"


# ------------------------------------------------------------------------------------------------------ worker
class Worker:
    """Claims training jobs and runs them, one at a time (see the module docstring for the whole contract).

    Args:
        settings: the service settings (job database, data folders, lease and heartbeat times).
        device: ``"cpu"`` or ``"cuda"``: where the rasterization step trains (checked now: a missing backend
            fails here, before any job is claimed).
        worker_id: the lease owner name (default :func:`default_worker_id`).
        store: a job store to use (default: ``JobStore.open(settings.jobs_database_url)``, closed by
            :meth:`close`).
        metrics: the metrics to update (default: new ones in their own registry).
        preview_every: iterations between previews (default: the job's checkpoint interval; 0: none).

    Thread-safety: one :meth:`run` / :meth:`run_one` at a time; the stop event may be set from any thread or a
    signal handler.
    """

    def __init__(self, settings: Settings, *, device: str = "cpu", worker_id: str | None = None,
                 store: JobStore | None = None, metrics: WorkerMetrics | None = None,
                 preview_every: int | None = None):
        raster_step(device)  # OptionError naming what is missing, before a job is claimed
        self.settings = settings
        hide_paths(settings.data_dir)  # the errors it records reach clients: no server path (service/errors.py)
        self.device = device
        self.worker_id = worker_id or default_worker_id()
        self._own_store = store is None
        self.store = store if store is not None else JobStore.open(settings.jobs_database_url)
        self.uploads = UploadStore(settings.upload_dir)
        self.bundles = BundleStore(settings.bundle_dir)
        self.metrics = metrics if metrics is not None else WorkerMetrics()
        self.preview_every = preview_every
        self._sweep_lock = threading.Lock()
        self._next_sweep = 0.0

    def close(self) -> None:
        if self._own_store:
            self.store.close()

    def __enter__(self) -> Worker:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- the loop ----
    def run(self, stop: threading.Event, *, max_jobs: int | None = None) -> None:
        """Work until ``stop`` is set: sweep expired leases every lease/2 seconds, claim the oldest queued job and
        train it, else wait for work (at most :data:`IDLE_WAIT_SECONDS` at a time, so a stop is noticed within
        about a second). Setting ``stop`` while a job trains hands it back (see the module docstring).
        ``max_jobs``: return after that many jobs (``--once``: 1; it waits for the first)."""
        done = 0
        log.info("worker %s: started (device %s, jobs %s, data %s)", self.worker_id, self.device,
                 redacted(self.settings.jobs_database_url), self.settings.data_dir)
        while not stop.is_set() and (max_jobs is None or done < max_jobs):
            try:
                self._maybe_sweep()
                job = self.store.claim(self.worker_id, self.settings.job_lease_seconds)
                if job is None:
                    wait = min(IDLE_WAIT_SECONDS, max(0.05, self._next_sweep - time.monotonic()))
                    self.store.wait_for_work(wait)
                    continue
            except (SQLAlchemyError, OSError) as exc:
                log.error("worker %s: the job database failed (%s); retrying in %.0f s", self.worker_id,
                          error_text(exc), DB_RETRY_SECONDS)
                stop.wait(DB_RETRY_SECONDS)
                continue
            self.process(job, stop)
            done += 1
        log.info("worker %s: stopped after %d job(s)", self.worker_id, done)

    def run_one(self, stop: threading.Event | None = None) -> Job | None:
        """Sweep, claim one queued job (no waiting) and train it; the job as the store has it afterwards (None
        when nothing was queued, or the job was deleted meanwhile)."""
        self._maybe_sweep(force=True)
        job = self.store.claim(self.worker_id, self.settings.job_lease_seconds)
        if job is None:
            return None
        self.process(job, stop or threading.Event())
        try:
            return self.store.get(job.id)
        except NotFound:
            return None

    def _maybe_sweep(self, force: bool = False) -> None:
        """Sweep expired leases when lease/2 seconds passed since the last sweep (the loop and the heartbeat
        thread both call it, so leases are swept while this worker trains too)."""
        with self._sweep_lock:
            now = time.monotonic()
            if not force and now < self._next_sweep:
                return
            self._next_sweep = now + self.settings.job_lease_seconds / 2
        try:
            changed = self.store.sweep()
        except (SQLAlchemyError, OSError) as exc:
            log.warning("worker %s: sweep failed (%s)", self.worker_id, error_text(exc))
            return
        if changed:
            log.info("worker %s: swept %d job(s) whose lease expired: %s", self.worker_id, len(changed),
                     ", ".join(changed))

    # ---- one job ----
    def process(self, job: Job, stop: threading.Event) -> str:
        """Train a job this worker has claimed, to its end; returns how the attempt ended (``succeeded``,
        ``failed``, ``cancelled``, ``released`` or ``lost``)."""
        started = time.monotonic()
        log.info("job %s: claimed by %s (attempt %d of %d)", job.id, self.worker_id, job.attempts, job.max_attempts)
        attempt = Attempt(self, job, stop)
        attempt.start()
        run = JobRun(self, job, attempt)
        try:
            state = run.train()
        except LeaseLost:
            log.warning("job %s: no longer ours (swept, finished elsewhere or deleted): stopped without a final "
                        "checkpoint, nothing committed", job.id)
            state = "lost"
        except Exception as exc:  # anything the job raised: it fails with the reason
            log.exception("job %s: failed", job.id)
            attempt.finish_heartbeats()
            state = run.end(JobState.FAILED, error=error_text(exc))
        finally:
            attempt.finish_heartbeats()
            self.metrics.iterations_per_second.set(0)
        if state != "lost":  # the work folder as this attempt left it (a lost job is someone else's to record)
            run.quota.measure(check=False)
        seconds = time.monotonic() - started
        self.metrics.jobs_finished.labels(state).inc()
        self.metrics.job_seconds.labels(state).observe(seconds)
        log.info("job %s: %s after %.1f s", job.id, state, seconds)
        return state


# ------------------------------------------------------------------------------------------------- the command
def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``blendsplat worker`` (what :func:`main` reads): ``--device``, ``--data-dir``,
    ``--jobs-url``, ``--worker-id``, ``--once``, ``--metrics-port``."""
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                        help="where training's rasterization step runs (default: cpu)")
    parser.add_argument("--data-dir", type=Path, default=None,
                        help="the data folder (uploads, work folders, bundle store, face models; default: "
                             "BLENDSPLAT_DATA_DIR or ./data)")
    parser.add_argument("--jobs-url", default=None,
                        help="job database URL (default: BLENDSPLAT_JOBS_URL or the SQLite file <data-dir>/jobs.db)")
    parser.add_argument("--worker-id", default=None,
                        help="the name leases are taken under (default: <hostname>-<pid>-<random>)")
    parser.add_argument("--once", action="store_true",
                        help="wait for one job, train it to its end and exit")
    parser.add_argument("--metrics-port", type=int, default=0,
                        help="serve Prometheus metrics on this port (0: no metrics server)")
    return parser


def main(args: argparse.Namespace) -> int:
    """Run a worker until SIGTERM or SIGINT (or, with ``once``, one job); 0 on a clean stop.

    A signal stops the job in training at the next iteration boundary; the Trainer checkpoints and the job is
    handed back (``release``: queued again, the attempt not counted), then the process exits 0."""
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    overrides: dict[str, Any] = {}
    if getattr(args, "data_dir", None) is not None:
        overrides["data_dir"] = args.data_dir
    if getattr(args, "jobs_url", None) is not None:
        overrides["jobs_url"] = args.jobs_url
    settings = Settings(**overrides)
    stop = threading.Event()

    def on_signal(signum, _frame) -> None:
        if not stop.is_set():
            log.info("%s: stopping (the job in training is checkpointed and handed back)",
                     signal.Signals(signum).name)
        stop.set()

    previous = {}
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGTERM, signal.SIGINT):
            previous[signum] = signal.signal(signum, on_signal)
    metrics = WorkerMetrics()
    server = None
    try:
        with Worker(settings, device=args.device, worker_id=args.worker_id, metrics=metrics) as worker:
            if args.metrics_port:
                from prometheus_client import start_http_server

                server, _ = start_http_server(args.metrics_port, registry=metrics.registry)
                log.info("worker %s: metrics on port %d", worker.worker_id, args.metrics_port)
            worker.run(stop, max_jobs=1 if args.once else None)
    finally:
        if server is not None:
            server.shutdown()
            server.server_close()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(add_arguments(argparse.ArgumentParser(
        prog="python -m service.jobs.worker", description="the blendsplat training worker")).parse_args()))
