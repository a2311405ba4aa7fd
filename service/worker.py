"""The training worker (``blendsplat worker``): claims jobs from the job store and drives the :class:`Trainer`.

One process trains one job at a time (one GPU per worker in production). The job table is the only record of a
job (:mod:`service.jobs.store` states its contract); this module is its consumer::

    loop:  sweep() every lease/2 seconds (expired leases: requeued or failed)
           claim() the oldest queued job, else wait_for_work() (PostgreSQL LISTEN, SQLite short polling)
    job:   spec -> dataset folder of the upload, face model, Trainer (resumed from the work folder's checkpoint
           when there is one or the job is on a later attempt) -> Trainer.run() -> Trainer.finish() -> the bundle
           committed to the bundle store under the spec's avatar id -> finish(succeeded, result)

**The job spec** (JSON, the job row's ``spec``; the REST side writes it)::

    {"upload_id": str, "preset": "tiny" | "paper", "iterations": int | null, "avatar_id": str,
     "resolution": int | null, "seed": int (default 0),
     "checkpoint_every": int | null, "gaussians": int | null, "mouth": int | null}   # optional, see below

``resolution`` (downscale the longest image side) is accepted and ignored: the portable dataset reader has no
cheap downscale, so the job trains at the dataset's resolution and says so in a ``log`` event. The optional
``checkpoint_every`` (iterations between checkpoints, default the preset's; previews follow it) and
``gaussians`` / ``mouth`` (initial face / mouth-interior Gaussians, default the preset's) override the preset for
a fresh start; a resumed job keeps its checkpoint's preset. The REST side need not expose them: they exist so that
short jobs (tests, experiments) can checkpoint often and start small. Unknown keys are ignored (logged), known
ones are checked and a bad value fails the job naming the key.

**The work folder** ``<settings.work_dir>/<job id>/`` is the Trainer's workdir (``checkpoints/``, ``log.jsonl``,
``summary.json``, ``curves.png``, ``report.json`` and ``contact_sheet.png`` when the dataset has held-out frames)
plus ``preview.png`` (the latest preview, replaced atomically every ``preview_every`` iterations, default every
checkpoint, and once more at the end of a finished training) and ``avatar.bundle`` (the trained bundle; a copy of
it is what enters the bundle store). The REST side serves these files as the job's artefacts.

**What a running job records**

- heartbeats every ``settings.heartbeat_seconds`` (a background thread) extend the lease by
  ``settings.job_lease_seconds`` and carry the latest progress when it changed: ``iteration``,
  ``total_iterations``, ``fraction``, ``eta_seconds``, ``loss``, ``psnr``, ``gaussians`` (throttled to the heartbeat
  interval, not every step; one more report when training ends);
- ``set_checkpoint(<work folder>/checkpoints/ckpt_<iteration>.pt)`` after each checkpoint;
- a ``preview`` event ``{"iteration": i, "path": "preview.png"}`` after each preview;
- ``log`` events: ``{"resumed_from": iteration, ...}`` when it resumed, the resolution note, and the reason
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
import dataclasses
import logging
import math
import numbers
import os
import secrets
import shutil
import signal
import socket
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError

from render_core.atomic import publish
from render_core.train.presets import PRESETS, get_preset
from render_core.train.trainer import Outcome, Progress, Trainer, last_checkpoint, raster_step

from .auth import ADMIN_TENANT, PermissionDenied
from .errors import InvalidArgument, NotFound
from .jobs import EventKind, Job, JobState, JobStore
from .jobs.models import JobRecord
from .settings import Settings
from .store import BundleStore, Owner, check_id
from .uploads import UploadStore, check_upload_id

__all__ = ["JobSpec", "Worker", "WorkerMetrics", "add_arguments", "default_worker_id", "main"]

log = logging.getLogger("service.worker")  # the same name when run as __main__

MAX_ERROR_CHARS = 2000
PREVIEW = "preview.png"
TRUTH = "truth.png"  # the dataset's image of the preview's frame (written with the first preview)
BUNDLE = "avatar.bundle"
IDLE_WAIT_SECONDS = 1.0  # longest single wait for work: how soon an idle worker notices ``stop``
DB_RETRY_SECONDS = 2.0  # back-off after the job database failed in the loop
_JOB_BUCKETS = (1, 5, 10, 30, 60, 120, 300, 600, 1200, 1800, 3600, 7200, 14400, 28800, 86400)
_SPEC_KEYS = {"upload_id", "preset", "iterations", "avatar_id", "resolution", "seed", "checkpoint_every", "gaussians",
              "mouth"}


def default_worker_id() -> str:
    """``<hostname>-<pid>-<random>``: unique per process, readable in the job table."""
    return f"{socket.gethostname()}-{os.getpid()}-{secrets.token_hex(3)}"


def _error_text(exc: BaseException) -> str:
    text = f"{type(exc).__name__}: {exc}"
    return text if len(text) <= MAX_ERROR_CHARS else text[: MAX_ERROR_CHARS - 3] + "..."


# ----------------------------------------------------------------------------------------------------- the spec
def _optional_int(spec: Mapping[str, Any], key: str, minimum: int) -> int | None:
    value = spec.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise InvalidArgument(f"expected an integer >= {minimum} or null, got {value!r}", field=f"spec.{key}")
    return int(value)


@dataclasses.dataclass(frozen=True)
class JobSpec:
    """A job's spec, checked (see the module docstring for the keys). :meth:`parse` raises InvalidArgument
    naming the key (``spec.<key>``)."""

    upload_id: str
    preset: str
    iterations: int | None
    avatar_id: str
    resolution: int | None = None
    seed: int = 0
    checkpoint_every: int | None = None
    gaussians: int | None = None
    mouth: int | None = None

    @classmethod
    def parse(cls, spec: Mapping[str, Any]) -> JobSpec:
        if not isinstance(spec, Mapping):
            raise InvalidArgument(f"expected a JSON object, got {type(spec).__name__}", field="spec")
        unknown = sorted(set(spec) - _SPEC_KEYS)
        if unknown:
            log.info("job spec: ignoring unknown keys %s", unknown)
        upload_id = check_upload_id(spec.get("upload_id"), field="spec.upload_id")
        preset = spec.get("preset", "tiny")
        if preset not in PRESETS:
            raise InvalidArgument(f"unknown preset {preset!r}; available: {', '.join(PRESETS)}", field="spec.preset")
        avatar_id = spec.get("avatar_id")
        if not isinstance(avatar_id, str):
            raise InvalidArgument(f"expected an avatar id, got {avatar_id!r}", field="spec.avatar_id")
        check_id(avatar_id, field="spec.avatar_id")
        seed = spec.get("seed")
        seed = 0 if seed is None else _optional_int(spec, "seed", 0)
        return cls(upload_id=upload_id, preset=preset, iterations=_optional_int(spec, "iterations", 1),
                   avatar_id=avatar_id, resolution=_optional_int(spec, "resolution", 1), seed=seed,
                   checkpoint_every=_optional_int(spec, "checkpoint_every", 1),
                   gaussians=_optional_int(spec, "gaussians", 1), mouth=_optional_int(spec, "mouth", 1))

    def preset_overrides(self) -> dict[str, int]:
        names = ("checkpoint_every", "gaussians", "mouth")
        return {k: getattr(self, k) for k in names if getattr(self, k) is not None}


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
class _LeaseLost(Exception):
    """Raised out of the Trainer's cancel check when the job is no longer ours: :meth:`Trainer.run` then ends
    without its final checkpoint, so a worker that lost its lease writes nothing more to a work folder that
    another worker may own by now."""


class _Attempt:
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
            log.warning("job %s: heartbeat failed (%s); retrying at the next interval", job.id, _error_text(exc))
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
                log.warning("job %s: cannot read the cancel flag (%s)", self.job.id, _error_text(exc))
                self._warned = now
            return True, False
        if row is None:
            return False, False
        owned = row.state == JobState.RUNNING.value and row.lease_owner == w.worker_id
        return owned, bool(row.cancel_requested)

    def should_stop(self) -> bool:
        """The Trainer's ``should_cancel``, asked before every iteration: True on shutdown or a cancel (noted by a
        heartbeat, or read from the row now); :class:`_LeaseLost` when the job is no longer ours."""
        if self.lost.is_set():
            raise _LeaseLost(self.job.id)
        if self.stop.is_set() or self.cancel.is_set():
            return True
        owned, cancel = self.control()
        if not owned:
            self.lost.set()
            raise _LeaseLost(self.job.id)
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
                 _redacted(self.settings.jobs_database_url), self.settings.data_dir)
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
                          _error_text(exc), DB_RETRY_SECONDS)
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
            log.warning("worker %s: sweep failed (%s)", self.worker_id, _error_text(exc))
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
        attempt = _Attempt(self, job, stop)
        attempt.start()
        try:
            state = self._train(job, attempt)
        except _LeaseLost:
            log.warning("job %s: no longer ours (swept, finished elsewhere or deleted): stopped without a final "
                        "checkpoint, nothing committed", job.id)
            state = "lost"
        except Exception as exc:  # anything the job raised: it fails with the reason
            log.exception("job %s: failed", job.id)
            attempt.finish_heartbeats()
            state = self._end(job, attempt, JobState.FAILED, error=_error_text(exc))
        finally:
            attempt.finish_heartbeats()
            self.metrics.iterations_per_second.set(0)
        seconds = time.monotonic() - started
        self.metrics.jobs_finished.labels(state).inc()
        self.metrics.job_seconds.labels(state).observe(seconds)
        log.info("job %s: %s after %.1f s", job.id, state, seconds)
        return state

    def _end(self, job: Job, attempt: _Attempt, state: JobState, *, error: str | None = None,
             result: dict | None = None) -> str:
        """finish() the job as ``state``; ``lost`` when it is no longer ours."""
        if attempt.lost.is_set():
            return "lost"
        try:
            ok = self.store.finish(job.id, self.worker_id, state, error=error, result=result)
        except (SQLAlchemyError, OSError):
            log.exception("job %s: could not record it as %s (the lease will expire and the job be retried)",
                          job.id, state)
            return "lost"
        if not ok:
            log.warning("job %s: not ours any more; it was not marked %s", job.id, state)
            return "lost"
        return state.value

    def _event(self, job: Job, kind: EventKind, data: dict) -> None:
        try:
            self.store.add_event(job.id, kind, data)
        except NotFound:
            pass  # deleted: the heartbeat or the next iteration's check stops the job
        except (SQLAlchemyError, OSError) as exc:
            log.warning("job %s: could not record a %s event (%s)", job.id, kind, _error_text(exc))

    def _set_checkpoint(self, job: Job, attempt: _Attempt, path: Path | None) -> None:
        """Record the work folder's last checkpoint on the row (once per file)."""
        if path is None or path == attempt.checkpoint:
            return
        try:
            if self.store.set_checkpoint(job.id, self.worker_id, str(path)):
                attempt.checkpoint = path
            else:
                attempt.lost.set()
        except (SQLAlchemyError, OSError) as exc:
            log.warning("job %s: could not record the checkpoint (%s)", job.id, _error_text(exc))

    def dataset(self, upload_id: str) -> tuple[Path, str]:
        """The dataset folder of an upload and the face model it was tracked with; NotFound saying the upload is
        gone."""
        try:
            return self.uploads.path(upload_id), self.uploads.get(upload_id).face_model
        except NotFound:
            raise NotFound(f"the upload {upload_id!r} does not exist (deleted, or expired under the retention "
                           "period): nothing to train on", field="spec.upload_id") from None

    def facemodel(self, name: str) -> Path | None:
        """The face-model file for a dataset tracked with ``name``: None for the open head (shipped with the
        install), else the first ``<settings.facemodel_dir>/<name>.*``; NotFound naming the folder if none."""
        from render_core.facemodel.open_head import NAME

        if name == NAME:
            return None
        folder = self.settings.facemodel_dir
        prefix = name + "."
        found = sorted(p for p in folder.iterdir() if p.name.startswith(prefix) and p.is_file()) \
            if folder.is_dir() else []
        if not found:
            raise NotFound(f"the dataset was tracked with face model {name!r}, which does not ship with blendsplat: "
                           f"put its face-model file at {folder}/{name}.<ext> (e.g. one made by `blendsplat facemodel "
                           f"import-flame`); {folder} has none", field="face_model")
        return found[0]

    def _train(self, job: Job, attempt: _Attempt) -> str:
        spec = JobSpec.parse(job.spec)
        data_dir, face_model = self.dataset(spec.upload_id)
        facemodel = self.facemodel(face_model)
        workdir = self.settings.work_dir / job.id
        workdir.mkdir(parents=True, exist_ok=True)
        if spec.resolution is not None:
            self._event(job, EventKind.LOG, {
                "message": f"resolution {spec.resolution} ignored: the dataset trains at its own resolution (the "
                           "dataset reader has no cheap downscale)", "resolution": spec.resolution})
        preset = get_preset(spec.preset)
        if spec.preset_overrides():
            preset = preset.with_(**spec.preset_overrides())
        trainer = Trainer(data_dir, workdir, preset, device=self.device, seed=spec.seed, iterations=spec.iterations,
                          facemodel=facemodel)
        if job.attempts > 1 or last_checkpoint(workdir) is not None:
            if trainer.resume():
                log.info("job %s: resumed from iteration %d", job.id, trainer.iteration)
                self._event(job, EventKind.LOG, {"message": f"resumed from iteration {trainer.iteration}",
                                                 "resumed_from": trainer.iteration, "attempt": job.attempts})
            else:
                self._event(job, EventKind.LOG, {"message": "no checkpoint: starting from scratch",
                                                 "resumed_from": 0, "attempt": job.attempts})
        every = trainer.preset.checkpoint_every
        preview_every = every if self.preview_every is None else self.preview_every
        last_preview = [0]

        def on_progress(event: Progress) -> None:
            attempt.record(event)
            if event.preview is not None:
                self._write_preview(job, workdir, event.iteration, event.preview, trainer)
                last_preview[0] = event.iteration
            if event.iteration % every == 0:
                self._set_checkpoint(job, attempt, last_checkpoint(workdir))

        outcome = trainer.run(on_progress=on_progress, should_cancel=attempt.should_stop,
                              preview_every=preview_every)
        self._set_checkpoint(job, attempt, last_checkpoint(workdir))  # run() checkpoints when it ends
        attempt.beat()  # the last progress on the row (and a final look at the lease and the cancel flag)
        if outcome is not Outcome.FINISHED or attempt.stop.is_set() or attempt.lost.is_set():
            return self._stop_early(job, attempt, trainer.iteration)
        if preview_every and last_preview[0] != trainer.iteration:
            self._write_preview(job, workdir, trainer.iteration, trainer.preview(), trainer)
        summary = trainer.finish(workdir / BUNDLE)
        attempt.refresh()
        if attempt.lost.is_set() or attempt.cancel.is_set():
            return self._stop_early(job, attempt, trainer.iteration)
        manifest = self._commit(workdir / BUNDLE, spec.avatar_id, job.tenant)
        ev = summary.get("eval")
        evaluation = None if not ev else {k: ev[k] for k in ("psnr", "ssim", "psnr_head") if ev.get(k) is not None}
        result = {"avatar_id": spec.avatar_id, "digest": manifest["digest"], "evaluation": evaluation,
                  "final_psnr": summary["final"]["psnr_mean"], "iterations": trainer.iteration,
                  "seconds": round(trainer.elapsed, 3)}
        attempt.finish_heartbeats()
        state = self._end(job, attempt, JobState.SUCCEEDED, result=result)
        if state == "lost":
            log.warning("job %s: the avatar %r was committed but the job was no longer ours", job.id, spec.avatar_id)
        return state

    def _stop_early(self, job: Job, attempt: _Attempt, iteration: int) -> str:
        """Training stopped before its end or before the commit: lost (touch nothing), cancelled, or handed
        back."""
        if attempt.lost.is_set():
            log.warning("job %s: stopped at iteration %d: the lease is lost; nothing committed", job.id, iteration)
            return "lost"
        attempt.refresh()
        if attempt.lost.is_set():
            return "lost"
        if attempt.cancel.is_set():
            self._event(job, EventKind.LOG, {"message": f"cancelled at iteration {iteration}", "iteration": iteration})
            attempt.finish_heartbeats()
            return self._end(job, attempt, JobState.CANCELLED, error=f"cancelled at iteration {iteration}")
        self._event(job, EventKind.LOG, {"message": f"worker shutting down: handed back at iteration {iteration}",
                                         "iteration": iteration, "worker": self.worker_id})
        attempt.finish_heartbeats()
        try:
            released = self.store.release(job.id, self.worker_id)
        except (SQLAlchemyError, OSError):
            log.exception("job %s: could not hand it back (the lease will expire and the job be retried)", job.id)
            return "lost"
        if not released:
            return "lost"
        log.info("job %s: handed back at iteration %d", job.id, iteration)
        return "released"

    def _write_preview(self, job: Job, workdir: Path, iteration: int, pixels, trainer: Trainer) -> None:
        """``preview.png``, replaced atomically, and a ``preview`` event; with the first one, ``truth.png`` (the
        dataset's image of the same frame, shown beside it)."""
        if not (workdir / TRUTH).exists():
            self._write_image(job, workdir, TRUTH, trainer.preview_truth())
        if not self._write_image(job, workdir, PREVIEW, pixels):
            return
        self._event(job, EventKind.PREVIEW, {"iteration": iteration, "path": PREVIEW})

    @staticmethod
    def _write_image(job: Job, workdir: Path, name: str, pixels) -> bool:
        """An image of the work folder, replaced atomically (written beside under a ``.png`` name, then renamed);
        False (logged) when it could not be written."""
        from render_core.media.files import write_image

        tmp = workdir / f".{name}.{secrets.token_hex(6)}.png"
        try:
            write_image(tmp, pixels)
            publish(tmp, workdir / name)
            return True
        except OSError as exc:
            log.warning("job %s: could not write %s (%s)", job.id, name, _error_text(exc))
            return False
        finally:
            tmp.unlink(missing_ok=True)

    def _commit(self, bundle: Path, avatar_id: str, tenant: str | None) -> dict:
        """A copy of the trained bundle into the bundle store under ``avatar_id`` (validated, published atomically,
        recorded as verified, owned by the job's tenant); the manifest. PermissionDenied when the id is taken by
        another tenant's avatar meanwhile (checked at submission too)."""
        owner = Owner(tenant or ADMIN_TENANT)
        existing = self.bundles.owner_if_exists(avatar_id)
        if existing is not None and tenant is not None and existing.tenant != tenant:
            raise PermissionDenied(f"avatar {avatar_id!r} belongs to another tenant; not replaced",
                                   field="avatar_id")
        fd, staged = self.bundles.staging()
        try:
            with os.fdopen(fd, "wb") as out, open(bundle, "rb") as src:
                shutil.copyfileobj(src, out, 1 << 20)
        except BaseException:
            staged.unlink(missing_ok=True)
            raise
        manifest = self.bundles.commit(staged, avatar_id, owner)
        log.info("avatar %r committed to the bundle store (%s)", avatar_id, manifest.get("digest"))
        return manifest


def _redacted(url: str) -> str:
    """A database URL without its password (for logs)."""
    try:
        from sqlalchemy.engine import make_url

        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # noqa: BLE001 - only for a log line
        return "<job database>"


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
        prog="python -m service.worker", description="the blendsplat training worker")).parse_args()))
