"""One claimed job trained to its end (:class:`JobRun`): spec, dataset (a video upload's tracked first:
:mod:`service.jobs.track`), face model, Trainer, previews, checkpoints, the commit and the job's final state. The
worker's contract is :mod:`service.jobs.worker`'s docstring; :class:`~service.jobs.attempt.Attempt` is the lease and
cancel side of the same job.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy.exc import SQLAlchemyError

from render_core.data.portable import MANIFEST
from render_core.train.presets import get_preset
from render_core.train.trainer import Outcome, Progress, Trainer, last_checkpoint

from ..errors import NotFound
from .artefacts import BUNDLE, PREVIEW, TRUTH, commit_bundle, write_image
from .attempt import Attempt, error_text
from .models import EventKind, Job, JobState
from .quota import WorkQuota
from .resize import dataset_at
from .schemas import JobSpec
from .track import TrackInterrupted, tracked_dataset
from .uploads import UploadStore

if TYPE_CHECKING:
    from .worker import Worker

log = logging.getLogger("service.jobs.worker")  # the worker's log (the same name when it runs as __main__)


def dataset_of(uploads: UploadStore, upload_id: str) -> tuple[Path, str]:
    """The dataset folder of an upload and the face model it was tracked with; NotFound saying the upload is
    gone."""
    try:
        return uploads.path(upload_id), uploads.get(upload_id).face_model
    except NotFound:
        raise _gone(upload_id) from None


def _gone(upload_id: str) -> NotFound:
    return NotFound(f"the upload {upload_id!r} does not exist (deleted, or expired under the retention period): "
                    "nothing to train on", field="spec.upload_id")


def facemodel_file(folder: Path, name: str) -> Path | None:
    """The face-model file for a dataset tracked with ``name``: None for the open head (shipped with the
    install), else the first ``<folder>/<name>.*`` (``folder``: ``settings.facemodel_dir``); NotFound naming the
    folder if none."""
    from render_core.facemodel.open_head import NAME

    if name == NAME:
        return None
    prefix = name + "."
    found = sorted(p for p in folder.iterdir() if p.name.startswith(prefix) and p.is_file()) \
        if folder.is_dir() else []
    if not found:
        raise NotFound(f"the dataset was tracked with face model {name!r}, which does not ship with blendsplat: "
                       f"put its face-model file at {folder}/{name}.<ext> (e.g. one made by `blendsplat facemodel "
                       f"import-flame`); {folder} has none", field="face_model")
    return found[0]


class JobRun:
    """A job the worker has claimed (``job``, leased under ``attempt``), trained in its work folder."""

    def __init__(self, worker: Worker, job: Job, attempt: Attempt):
        self.worker, self.job, self.attempt = worker, job, attempt
        self.workdir = worker.settings.work_dir / job.id
        self.quota = WorkQuota(worker, job, self.workdir)  # measured at checkpoints and stage ends

    def end(self, state: JobState, *, error: str | None = None, result: dict | None = None) -> str:
        """finish() the job as ``state``; ``lost`` when it is no longer ours."""
        if self.attempt.lost.is_set():
            return "lost"
        try:
            ok = self.worker.store.finish(self.job.id, self.worker.worker_id, state, error=error, result=result)
        except (SQLAlchemyError, OSError):
            log.exception("job %s: could not record it as %s (the lease will expire and the job be retried)",
                          self.job.id, state)
            return "lost"
        if not ok:
            log.warning("job %s: not ours any more; it was not marked %s", self.job.id, state)
            return "lost"
        return state.value

    def event(self, kind: EventKind, data: dict) -> None:
        try:
            self.worker.store.add_event(self.job.id, kind, data)
        except NotFound:
            pass  # deleted: the heartbeat or the next iteration's check stops the job
        except (SQLAlchemyError, OSError) as exc:
            log.warning("job %s: could not record a %s event (%s)", self.job.id, kind, error_text(exc))

    def _set_checkpoint(self, path: Path | None) -> None:
        """Record the work folder's last checkpoint on the row (once per file)."""
        if path is None or path == self.attempt.checkpoint:
            return
        try:
            if self.worker.store.set_checkpoint(self.job.id, self.worker.worker_id, str(path)):
                self.attempt.checkpoint = path
            else:
                self.attempt.lost.set()
        except (SQLAlchemyError, OSError) as exc:
            log.warning("job %s: could not record the checkpoint (%s)", self.job.id, error_text(exc))

    def train(self) -> str:
        """Train the job to its end: the state it ended in (see :meth:`~service.jobs.worker.Worker.process`)."""
        job, attempt, w = self.job, self.attempt, self.worker
        spec = JobSpec.parse(job.spec)
        workdir = self.workdir
        workdir.mkdir(parents=True, exist_ok=True)
        try:
            data_dir, face_model, tracked = self._dataset(spec)
        except TrackInterrupted:
            return self._stop_early(0, "while the video was tracked")
        facemodel = facemodel_file(w.settings.facemodel_dir, face_model)
        if spec.resolution is not None:
            data_dir = self._at_resolution(data_dir, spec.resolution)
        self.quota.measure()  # a tracked or resampled dataset: StorageQuotaExceeded fails the job
        preset = get_preset(spec.preset)
        if spec.preset_overrides():
            preset = preset.with_(**spec.preset_overrides())
        if tracked:  # the tracker's poses and expressions: each training frame learns a correction of them
            preset = preset.with_(refine_poses=True, refine_expressions=True)
        trainer = Trainer(data_dir, workdir, preset, device=w.device, seed=spec.seed, iterations=spec.iterations,
                          facemodel=facemodel)
        if job.attempts > 1 or last_checkpoint(workdir) is not None:
            if trainer.resume():
                log.info("job %s: resumed from iteration %d", job.id, trainer.iteration)
                self.event(EventKind.LOG, {"message": f"resumed from iteration {trainer.iteration}",
                                           "resumed_from": trainer.iteration, "attempt": job.attempts})
            else:
                self.event(EventKind.LOG, {"message": "no checkpoint: starting from scratch",
                                           "resumed_from": 0, "attempt": job.attempts})
        every = trainer.preset.checkpoint_every
        preview_every = every if w.preview_every is None else w.preview_every
        last_preview = [0]

        def on_progress(event: Progress) -> None:
            attempt.record(event)
            if event.preview is not None:
                self._write_preview(event.iteration, event.preview, trainer)
                last_preview[0] = event.iteration
            if event.iteration % every == 0:
                self._set_checkpoint(last_checkpoint(workdir))
                self.quota.measure()

        outcome = trainer.run(on_progress=on_progress, should_cancel=attempt.should_stop,
                              preview_every=preview_every)
        self._set_checkpoint(last_checkpoint(workdir))  # run() checkpoints when it ends
        attempt.beat()  # the last progress on the row (and a final look at the lease and the cancel flag)
        if outcome is not Outcome.FINISHED or attempt.stop.is_set() or attempt.lost.is_set():
            return self._stop_early(trainer.iteration)
        if preview_every and last_preview[0] != trainer.iteration:
            self._write_preview(trainer.iteration, trainer.preview(), trainer)
        summary = trainer.finish(workdir / BUNDLE)
        self.quota.measure()  # the bundle and the report, before the commit
        attempt.refresh()
        if attempt.lost.is_set() or attempt.cancel.is_set():
            return self._stop_early(trainer.iteration)
        manifest = commit_bundle(w.bundles, workdir / BUNDLE, spec.avatar_id, job.tenant)
        ev = summary.get("eval")
        evaluation = None if not ev else {k: ev[k] for k in ("psnr", "ssim", "psnr_head") if ev.get(k) is not None}
        result = {"avatar_id": spec.avatar_id, "digest": manifest["digest"], "evaluation": evaluation,
                  "final_psnr": summary["final"]["psnr_mean"], "iterations": trainer.iteration,
                  "seconds": round(trainer.elapsed, 3)}
        attempt.finish_heartbeats()
        state = self.end(JobState.SUCCEEDED, result=result)
        if state == "lost":
            log.warning("job %s: the avatar %r was committed but the job was no longer ours", job.id, spec.avatar_id)
        return state

    def _dataset(self, spec: JobSpec) -> tuple[Path, str, bool]:
        """The dataset folder to train on, its face model and whether this job tracked it: the upload's, or for a
        video upload the one tracked from it in the work folder (an earlier attempt's, or tracked now:
        TrackInterrupted on a cancel or a shutdown meanwhile)."""
        uploads = self.worker.uploads
        try:
            upload = uploads.get(spec.upload_id)
            if upload.kind != "video":
                return uploads.path(spec.upload_id), upload.face_model, False
            video = uploads.video_path(spec.upload_id)
        except NotFound:
            raise _gone(spec.upload_id) from None
        data_dir = tracked_dataset(self, video, upload, spec.resolution)
        manifest = json.loads((data_dir / MANIFEST).read_text(encoding="utf-8"))
        return data_dir, str(manifest.get("face_model") or upload.face_model), True

    def _stop_early(self, iteration: int, where: str | None = None) -> str:
        """Training stopped before its end or before the commit: lost (touch nothing), cancelled, or handed
        back. ``where``: when it stopped (default: at the iteration)."""
        at = where or f"at iteration {iteration}"
        if self.attempt.lost.is_set():
            log.warning("job %s: stopped %s: the lease is lost; nothing committed", self.job.id, at)
            return "lost"
        self.attempt.refresh()
        if self.attempt.lost.is_set():
            return "lost"
        if self.attempt.cancel.is_set():
            self.event(EventKind.LOG, {"message": f"cancelled {at}", "iteration": iteration})
            self.attempt.finish_heartbeats()
            return self.end(JobState.CANCELLED, error=f"cancelled {at}")
        self.event(EventKind.LOG, {"message": f"worker shutting down: handed back {at}",
                                   "iteration": iteration, "worker": self.worker.worker_id})
        self.attempt.finish_heartbeats()
        try:
            released = self.worker.store.release(self.job.id, self.worker.worker_id)
        except (SQLAlchemyError, OSError):
            log.exception("job %s: could not hand it back (the lease will expire and the job be retried)", self.job.id)
            return "lost"
        if not released:
            return "lost"
        log.info("job %s: handed back %s", self.job.id, at)
        return "released"

    def _write_preview(self, iteration: int, pixels, trainer: Trainer) -> None:
        """``preview.png``, replaced atomically, and a ``preview`` event; with the first one, ``truth.png`` (the
        dataset's image of the same frame, shown beside it)."""
        if not (self.workdir / TRUTH).exists():
            self._write_image(TRUTH, trainer.preview_truth())
        if self._write_image(PREVIEW, pixels):
            self.event(EventKind.PREVIEW, {"iteration": iteration, "path": PREVIEW})

    def _write_image(self, name: str, pixels) -> bool:
        """An image of the work folder, replaced atomically; False (logged) when it could not be written."""
        try:
            write_image(self.workdir, name, pixels)
            return True
        except OSError as exc:
            log.warning("job %s: could not write %s (%s)", self.job.id, name, error_text(exc))
            return False

    def _at_resolution(self, data_dir: Path, resolution: int) -> Path:
        """The dataset to train on at ``resolution`` (resampled into the work folder when it is larger), and a
        ``log`` event saying at which size it trains."""
        trained, (width, height), (own_width, own_height) = dataset_at(data_dir, resolution, self.workdir)
        if trained == data_dir:
            message = (f"resolution {resolution}: training at the dataset's own {own_width}x{own_height} (it is no "
                       "larger)")
        else:
            message = f"resolution {resolution}: training at {width}x{height} (the dataset is {own_width}x{own_height})"
        log.info("job %s: %s", self.job.id, message)
        self.event(EventKind.LOG, {"message": message, "resolution": resolution, "width": width, "height": height})
        return trained
