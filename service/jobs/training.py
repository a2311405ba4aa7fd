"""The training side of a service process: :class:`Training`, its stores and the operations that span them.

:class:`Training` holds the job store (:class:`~service.jobs.store.JobStore`), the upload store
(:class:`~service.jobs.uploads.UploadStore`), the process's access control (limits, audit) and the bundle store's
owner lookup, all given to its constructor: it is built complete, once per process (``service/server.py``), and the
routes (:mod:`service.jobs.api`) are thin over it. The job database is the source of truth of a job; its files live
in its work folder ``<settings.work_dir>/<job id>/``, written by the worker (:mod:`service.jobs.worker`).


**Deletion is real** (face video is biometric data):

- a job: its row and events go at once, then its work folder (checkpoints, previews, log, report, the bundle's
  copy; for a job from a video also the tracked dataset, its archive and the overlay). A worker training it finds
  the row gone before its next iteration (or its next tracking step) and stops without writing more and without
  committing; a file it was writing at that moment is removed by the next retention sweep (a work folder without a
  job row is an orphan);
- an upload: refused (409, the jobs named) while a queued or running job trains on it: cancel or delete those
  first. Otherwise its dataset (or video) goes, and with it the work folders of the finished jobs trained on it
  (their previews, contact sheets, overlays and tracked datasets show the face); those jobs' rows stay (no image
  data in them) and their artefacts answer 404. Avatars trained from it stay: they are deleted on their own;
- an avatar: its bundle and the store's verification record are removed and every cached copy in this process is
  dropped (other replicas find it gone at their next session; streams already open keep theirs until they end).
  The work folder of the job that trained it is the job's (DELETE the job, or retention);
- retention (:meth:`Training.sweep`, at start and every :data:`RETENTION_INTERVAL_SECONDS`): uploads older than
  ``upload_retention_hours`` (except those a queued or running job still needs) and the work folders of jobs that
  finished more than ``work_retention_hours`` ago (0: never by age); job rows are kept (they hold no image data and
  keep the job's history and result). Orphaned work folders and what killed processes left are removed too.

**Storage quota** (``tenant_storage_bytes``): a tenant's bundles, its uploads as extracted (measured at ingest) and
its jobs' work folders (measured by the worker at checkpoints and stage ends, recorded on the job's row,
``work_bytes``) are summed from those records, never by walking the disk. An upload is refused when what it stores
(or its files, ``tenant_max_files``) would pass the tenant's bounds; a job when the least its work folder will hold
would; a running job whose work folder takes the tenant past it fails (:mod:`service.jobs.quota`). A job submission
that replays an idempotency key (or conflicts with it: 409) is answered without counting against the key's jobs
per hour.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING

from ..access.auth import Access, Principal
from ..errors import FailedPrecondition, NotFound
from ..intake import UploadIntake
from ..settings import Settings
from ..store import Writer
from ..usage import Usage, tree_usage
from .archive import ArchiveLimits
from .artefacts import ARTEFACTS, TRACK_ARTEFACTS, job_writer, why_no_track_artefact
from .models import Job, JobState
from .quota import work_estimate
from .schemas import JobLinks, JobOut, JobSpec, Progress, WebhookOut
from .store import JobStore
from .uploads import Upload, UploadStore
from .video import video_limits

if TYPE_CHECKING:
    from ..metrics import Metrics

log = logging.getLogger(__name__)

RETENTION_INTERVAL_SECONDS = 300.0  # how often a service process runs the retention sweep
STALE_GRACE = timedelta(minutes=15)  # upload leftovers younger than this may be another process's upload in progress
ORPHAN_GRACE = timedelta(minutes=1)  # a work folder without a job row, untouched this long, is removed
_PAGE = 500  # jobs read per query when scanning


def open_stores(settings: Settings) -> tuple[JobStore, UploadStore]:
    """Open the job database (migrated to head) and the upload folder, and make the work folder; remove what
    killed processes left among the uploads (older than :data:`STALE_GRACE`, so another process's upload in
    progress is spared). The stores a :class:`Training` is built with."""
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    jobs = JobStore.open(settings.jobs_database_url)
    try:
        uploads = UploadStore(settings.upload_dir, limits=ArchiveLimits(
            max_extraction_ratio=settings.max_extraction_ratio), video_limits=video_limits(
            settings.max_video_seconds, settings.max_video_side, settings.max_video_frames))
        uploads.ensure()
        stale = uploads.clean_stale(STALE_GRACE)  # a dead process's at once; an older version's by age
        if stale:
            log.info("uploads: removed %d leftovers of interrupted uploads", stale)
        if uploads.empty_trash():
            log.info("uploads: removing the files of deletions a stopped process left (in the background)")
        Path(settings.work_dir).mkdir(parents=True, exist_ok=True)
    except BaseException:
        jobs.close()
        raise
    return jobs, uploads


@dataclass
class SweepReport:
    uploads: list[str]
    work_folders: list[str]
    stale: int


class Training:
    """The training side of a service process: its settings, job store and upload store, and the operations that
    span them. Synchronous (the stores are): async callers run it in a thread."""

    def __init__(self, settings: Settings, jobs: JobStore, uploads: UploadStore, *, access: Access,
                 writable: Callable[[str, Writer], object], metrics: Metrics | None = None):
        """``jobs`` and ``uploads``: from :func:`open_stores` (closed by :meth:`close`). ``access``: the process's
        access control (per-key limits, quotas, audit). ``writable``: the bundle store's one avatar-write rule
        (:meth:`~service.store.BundleStore.writable`: PermissionDenied when the writer may not write the id).
        ``metrics``: the process's; the job queue's depth
        is read from ``jobs`` at each scrape."""
        self.settings, self.jobs, self.uploads, self.metrics = settings, jobs, uploads, metrics
        self.access = access
        self.intake = UploadIntake(access)
        self.writable = writable
        self.work_root = Path(settings.work_dir)
        if metrics is not None:
            metrics.watch_jobs(jobs)

    # ------------------------------------------------------------------------------------------- ownership
    def job_for(self, job_id: str, principal: Principal) -> Job:
        """The job, when ``principal`` may see it (its tenant's; admin: any): NotFound, PermissionDenied."""
        job = self.jobs.get(job_id)
        principal.check_read(f"job {job_id}", job.tenant)
        return job

    def upload_for(self, upload_id: str, principal: Principal) -> Upload:
        upload = self.uploads.get(upload_id)
        principal.check_read(f"upload {upload_id}", upload.tenant)
        return upload

    def close(self) -> None:
        self.jobs.close()

    # ------------------------------------------------------------------------------------------------ jobs
    def submit(self, request: JobSpec, idempotency_key: str | None, principal: Principal) -> tuple[Job, bool]:
        """Queue a job for an existing upload; (the job, whether this call created it). A repeated
        ``idempotency_key`` with the same request returns the first job; with another, IdempotencyConflict.
        The job is the caller's tenant's: it trains on that tenant's upload, into an avatar id that is free or
        the tenant's own (PermissionDenied otherwise; the worker checks the avatar again when it commits)."""
        upload = self.upload_for(request.upload_id, principal)  # NotFound naming upload_id; PermissionDenied
        self.writable(request.avatar_id, job_writer(principal.tenant))  # the rule the worker's commit applies
        if idempotency_key is None or self.jobs.by_idempotency_key(principal.tenant, idempotency_key) is None:
            self.access.check_quota(principal, work_estimate(upload, request.resolution))
            self.access.count_job(principal)  # a replay or a 409 is not another job: not counted
        before = datetime.now(UTC)
        job = self.jobs.submit(request.stored(), tenant=principal.tenant, idempotency_key=idempotency_key,
                               max_attempts=self.settings.job_max_attempts)
        created = idempotency_key is None or job.created_at >= before
        if self.metrics is not None:
            self.metrics.jobs_submitted.labels("created" if created else "replayed").inc()
        return job, created

    def work_folder(self, job_id: str) -> Path:
        return self.work_root / job_id

    def admit_stored(self, principal: Principal, used: Usage) -> None:
        """An upload as it will be kept, before it is published: the tenant's quota and file bound (the upload
        store's ``admit``)."""
        self.access.check_stored(principal, used.bytes, used.files)

    def job_out(self, job: Job) -> JobOut:
        base = f"/v1/jobs/{job.id}"
        folder = self.work_folder(job.id)
        artefacts = {name: f"{base}/artefacts/{name}" for name, (file, _) in ARTEFACTS.items()
                     if self._servable(folder, file)}
        upload_id = job.spec.get("upload_id")
        avatar_id = (job.result or {}).get("avatar_id") if job.state is JobState.SUCCEEDED else None
        return JobOut(
            id=job.id, state=job.state, spec=job.spec, attempts=job.attempts, max_attempts=job.max_attempts,
            cancel_requested=job.cancel_requested,
            progress=Progress(fraction=job.fraction, iteration=job.iteration, total_iterations=job.total_iterations,
                              eta_seconds=job.eta_seconds, loss=job.loss, psnr=job.psnr, gaussians=job.gaussians),
            error=job.error, result=job.result, created_at=job.created_at, started_at=job.started_at,
            finished_at=job.finished_at, updated_at=job.updated_at,
            links=JobLinks(self=base, cancel=f"{base}/cancel",
                           upload=f"/v1/uploads/{upload_id}" if isinstance(upload_id, str) else None,
                           artefacts=artefacts, avatar=f"/v1/avatars/{avatar_id}" if avatar_id else None),
            webhooks=[WebhookOut(id=d.id, event=d.event, status=d.status.value, attempts=d.attempts,
                                 last_status=d.last_status, last_error=d.last_error, next_attempt_at=d.next_attempt_at,
                                 created_at=d.created_at, delivered_at=d.delivered_at)
                      for d in (self.jobs.deliveries(job.id) if job.spec.get("webhook_url") else ())])

    def artefact(self, job_id: str, name: str) -> tuple[Path, str]:
        """The file of a job's artefact and its media type; NotFound for an unknown job or name, or a file not
        (yet) written. Only the fixed file names of :data:`ARTEFACTS`, directly in the job's work folder."""
        job = self.jobs.get(job_id)  # NotFound: an id the database does not know never becomes a path
        if name not in ARTEFACTS:
            raise NotFound(f"no artefact {name!r}; a job's artefacts are {', '.join(ARTEFACTS)}", field="name")
        file, media_type = ARTEFACTS[name]
        folder = self.work_folder(job_id)
        if not self._servable(folder, file):
            raise NotFound(self._why_missing(job, name, file, folder), field="name")
        return folder / file, media_type

    def _why_missing(self, job: Job, name: str, file: str, folder: Path) -> str:
        """The 404 of a job's artefact that is not there, with the reason: not yet (queued, running), never
        (cancelled, failed, no held-out frames, figures the worker could not draw) or no longer (work folder gone)."""
        if name in TRACK_ARTEFACTS:
            return why_no_track_artefact(job, name, file, folder, self._upload_kind(job.spec.get("upload_id")))
        during = name in ("preview", "truth", "log")
        if job.state in (JobState.QUEUED, JobState.RUNNING):
            when = "as it trains" if during else "when training ends"
            return f"job {job.id} has no {name} yet ({file} is written by the worker {when})"
        return f"job {job.id} has no {name}: {self._why_never(job, name, file, folder, during)}"

    @staticmethod
    def _why_never(job: Job, name: str, file: str, folder: Path, during: bool) -> str:
        if not folder.is_dir():
            return ("its work folder is gone (removed by retention, work_retention_hours after the job finished, or "
                    "with the upload it trained on)")
        if job.state is JobState.CANCELLED and not during:
            return f"the job was cancelled before training ended ({file} is written when training finishes)"
        if job.state is JobState.FAILED and not during:
            return f"the job failed before training ended ({job.error or 'no error recorded'})"
        if job.state is JobState.SUCCEEDED and not during:
            summary = _read_json(folder / "summary.json")
            if name == "curves":
                skipped = (summary.get("plots") or {}).get("skipped")
                if skipped:
                    return f"the worker could not draw the training curves ({skipped})"
            elif name in ("report", "contact-sheet"):
                if summary and not summary.get("eval"):
                    return ("the dataset has no held-out (test) frames: the report and the contact sheet evaluate "
                            "the avatar on them")
                if name == "contact-sheet":
                    skipped = (_read_json(folder / "report.json").get("plots") or {}).get("skipped")
                    if skipped:
                        return f"the worker could not draw it ({skipped})"
        return f"the job {job.state.value} without writing {file}"

    def _upload_kind(self, upload_id) -> str | None:
        try:
            return self.uploads.get(upload_id).kind if isinstance(upload_id, str) else None
        except NotFound:
            return None

    def _servable(self, folder: Path, file: str) -> bool:
        """A regular file directly in the job's work folder (no symbolic link on the way is followed)."""
        path = folder / file
        return (not folder.is_symlink() and not path.is_symlink() and path.is_file()
                and path.parent.resolve() == self.work_root.resolve() / folder.name)

    def delete_job(self, job_id: str) -> None:
        """Delete a job whatever its state: its row and events, then its work folder. NotFound if there is none."""
        self.jobs.delete(job_id)
        self._remove_work(job_id)

    def _scan(self, state: JobState | None = None) -> Iterator[Job]:
        cursor = None
        while True:
            page, cursor = self.jobs.list(state=state, limit=_PAGE, cursor=cursor)
            yield from page
            if cursor is None:
                return

    def active_upload_ids(self) -> dict[str, list[str]]:
        """Uploads that queued or running jobs need: upload id -> those jobs' ids."""
        out: dict[str, list[str]] = {}
        for state in (JobState.QUEUED, JobState.RUNNING):
            for job in self._scan(state):
                upload_id = job.spec.get("upload_id")
                if isinstance(upload_id, str):
                    out.setdefault(upload_id, []).append(job.id)
        return out

    # --------------------------------------------------------------------------------------------- uploads
    def delete_upload(self, upload_id: str) -> list[str]:
        """Delete an upload and the work folders of the finished jobs trained on it; the ids of those jobs.
        NotFound if there is no such upload; FailedPrecondition (409) while a queued or running job uses it."""
        self.uploads.get(upload_id)
        users = self.active_upload_ids().get(upload_id)
        if users:
            shown = ", ".join(users[:10]) + (", ..." if len(users) > 10 else "")
            raise FailedPrecondition(f"upload {upload_id} is used by queued or running jobs ({shown}); cancel or "
                                     "delete them first", field="upload_id")
        self.uploads.delete(upload_id)
        removed = []
        for job_id in self._work_folder_ids():
            try:
                job = self.jobs.get(job_id)
            except NotFound:
                continue
            if job.spec.get("upload_id") == upload_id and self._remove_work(job_id):
                removed.append(job_id)
        return removed

    # ------------------------------------------------------------------------------------------- retention
    def sweep(self, now: datetime | None = None) -> SweepReport:
        """Retention: delete uploads older than ``upload_retention_hours`` (not those a queued or running job
        needs) and the work folders of jobs that finished more than ``work_retention_hours`` ago (0: never by
        age); remove orphaned work folders (no job row, untouched for :data:`ORPHAN_GRACE`) and what interrupted
        uploads and deletions left. Job rows are kept."""
        now = now or datetime.now(UTC)
        s = self.settings
        uploads: list[str] = []
        if s.upload_retention_hours > 0:
            cutoff = now - timedelta(hours=s.upload_retention_hours)
            expired = [u.id for u in self.uploads.list() if u.created_at < cutoff]
            if expired:
                needed = self.active_upload_ids()
                for upload_id in expired:
                    if upload_id in needed:
                        log.info("retention: upload %s expired but jobs %s still need it", upload_id,
                                 ", ".join(needed[upload_id]))
                        continue
                    try:
                        self.uploads.delete(upload_id)
                    except NotFound:
                        continue
                    uploads.append(upload_id)
        stale = self.uploads.clean_stale(STALE_GRACE)
        self.uploads.empty_trash()
        work: list[str] = []
        work_cutoff = now - timedelta(hours=s.work_retention_hours) if s.work_retention_hours > 0 else None
        for job_id in self._work_folder_ids():
            try:
                job = self.jobs.get(job_id)
            except NotFound:
                modified = datetime.fromtimestamp(self._mtime(self.work_folder(job_id)), UTC)
                if now - modified > ORPHAN_GRACE and self._remove_work(job_id):
                    log.info("retention: removed the orphaned work folder of deleted job %s", job_id)
                continue
            if work_cutoff is not None and job.finished and job.finished_at is not None \
                    and job.finished_at < work_cutoff and self._remove_work(job_id):
                work.append(job_id)
            elif job.work_bytes is None:  # written before the quota counted work folders: measured once
                self.jobs.set_work_bytes(job_id, tree_usage(self.work_folder(job_id)).bytes)
        stale += self._clean_work_leftovers()
        if self.metrics is not None:
            self.metrics.retention_deleted.labels("upload").inc(len(uploads))
            self.metrics.retention_deleted.labels("work_folder").inc(len(work))
        if uploads or work:
            log.info("retention: deleted %d uploads and %d work folders", len(uploads), len(work))
        return SweepReport(uploads=uploads, work_folders=work, stale=stale)

    # ----------------------------------------------------------------------------------------- work folders
    def _work_folder_ids(self) -> list[str]:
        if not self.work_root.is_dir():
            return []
        return sorted(p.name for p in self.work_root.iterdir()
                      if p.name.startswith("job_") and p.is_dir() and not p.is_symlink())

    @staticmethod
    def _mtime(path: Path) -> float:
        try:
            return path.stat().st_mtime
        except OSError:
            return time.time()

    def _remove_work(self, job_id: str) -> bool:
        """Rename the job's work folder out of sight (``.deleting-*``), then remove it; False if there was none."""
        doomed = self.work_root / f".deleting-{job_id}-{secrets.token_hex(4)}"
        try:
            os.rename(self.work_folder(job_id), doomed)
        except FileNotFoundError:
            return False
        shutil.rmtree(doomed, ignore_errors=True)
        self.jobs.set_work_bytes(job_id, 0)  # no longer stored (a deleted job's row is gone: nothing to do)
        return True

    def _clean_work_leftovers(self) -> int:
        count = 0
        if self.work_root.is_dir():
            for p in self.work_root.iterdir():
                if p.name.startswith(".deleting-"):
                    shutil.rmtree(p, ignore_errors=True)
                    count += 1
        return count


def _read_json(path: Path) -> dict:
    """A work folder's JSON file as a dict; {} when it is missing or unreadable (an explanation, not a check)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}
