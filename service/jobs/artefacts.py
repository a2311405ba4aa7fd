"""A job's work folder ``<settings.work_dir>/<job id>/``: the files the worker writes there and the API serves, how
an image there is replaced, and the commit of the trained bundle to the bundle store.

The Trainer writes ``checkpoints/``, ``log.jsonl``, ``summary.json``, ``curves.png``, and ``report.json`` and
``contact_sheet.png`` when the dataset has held-out frames; the worker adds :data:`PREVIEW` (the latest preview,
replaced atomically), :data:`TRUTH` (the dataset's image of the preview's frame), :data:`BUNDLE` (the trained
bundle; a copy of it is what enters the bundle store) and, for a job with a ``resolution``, the resampled dataset
(:mod:`service.jobs.resize`). A job from a video upload also has its track stage's files (:mod:`service.jobs.track`):
``tracked/`` (the dataset it trains on), ``overlay.png``, ``dataset.tar.gz`` and ``track.json``.
:data:`ARTEFACTS` names the ones ``GET /v1/jobs/{id}/artefacts/{name}`` serves; :data:`TRACK_ARTEFACTS` those of the
track stage.
"""

from __future__ import annotations

import logging
import os
import secrets
import shutil
from pathlib import Path

from render_core.atomic import publish

from ..access.auth import ADMIN_TENANT
from ..store import BundleStore, Writer
from .models import Job, JobState
from .track import DATASET_ARCHIVE, OVERLAY, TRACK_REPORT

log = logging.getLogger(__name__)

PREVIEW = "preview.png"
TRUTH = "truth.png"  # the dataset's image of the preview's frame (written with the first preview)
BUNDLE = "avatar.bundle"
# name in the URL -> (file in the work folder, media type)
ARTEFACTS: dict[str, tuple[str, str]] = {  # in the order of the stages: track (a job from a video), then train
    "overlay": (OVERLAY, "image/png"),
    "dataset": (DATASET_ARCHIVE, "application/gzip"),
    "track-report": (TRACK_REPORT, "application/json"),
    "report": ("report.json", "application/json"),
    "summary": ("summary.json", "application/json"),
    "curves": ("curves.png", "image/png"),
    "contact-sheet": ("contact_sheet.png", "image/png"),
    "preview": (PREVIEW, "image/png"),
    "truth": (TRUTH, "image/png"),
    "log": ("log.jsonl", "application/x-ndjson"),
}
TRACK_ARTEFACTS = ("overlay", "dataset", "track-report")


def write_image(workdir: Path, name: str, pixels) -> None:
    """An image of the work folder (``pixels``: [H, W, 3] uint8), replaced atomically: written beside under a
    ``.png`` name, then renamed over ``name``. OSError when it could not be written (nothing is left behind)."""
    from render_core.media.files import write_image as write_file

    tmp = workdir / f".{name}.{secrets.token_hex(6)}.png"
    try:
        write_file(tmp, pixels)
        publish(tmp, workdir / name)
    finally:
        tmp.unlink(missing_ok=True)


def commit_bundle(bundles: BundleStore, bundle: Path, avatar_id: str, tenant: str | None) -> dict:
    """A copy of the trained bundle into the bundle store under ``avatar_id`` (validated, published atomically,
    recorded as verified) by the job's tenant, through the bundle store's one write rule
    (:meth:`~service.store.BundleStore.writable`: PermissionDenied when the id became another tenant's avatar
    meanwhile; a job an admin key submitted keeps an existing avatar's owner, as the avatar PUT does); the
    manifest."""
    staged = bundles.staging_path()
    try:
        fd = os.open(staged, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o600)
        with os.fdopen(fd, "wb") as out, open(bundle, "rb") as src:
            shutil.copyfileobj(src, out, 1 << 20)
    except BaseException:
        staged.unlink(missing_ok=True)
        raise
    manifest, _ = bundles.put(staged, avatar_id, job_writer(tenant))
    log.info("avatar %r committed to the bundle store (%s)", avatar_id, manifest.get("digest"))
    return manifest


def job_writer(tenant: str | None) -> Writer:
    """The writer of a job's avatar: the job's tenant; the admin tenant's jobs (and those of a server without
    keys) were submitted by admin keys (keys of the admin tenant always hold the admin scope)."""
    return Writer(tenant or ADMIN_TENANT, tenant in (None, ADMIN_TENANT))


def why_no_track_artefact(job: Job, name: str, file: str, folder: Path, upload_kind: str | None) -> str:
    """The 404 of a track-stage artefact (:data:`TRACK_ARTEFACTS`) that is not there, with the reason.
    ``upload_kind``: the job's upload's (``dataset``, ``video``; None when it is gone)."""
    if upload_kind == "dataset":
        return (f"job {job.id} has no {name}: it trains on an uploaded dataset (only a job from a video upload "
                "tracks one)")
    if job.state in (JobState.QUEUED, JobState.RUNNING):
        return f"job {job.id} has no {name} yet ({file} is written by the worker once the video is tracked)"
    if not folder.is_dir():
        return (f"job {job.id} has no {name}: its work folder is gone (removed by retention, work_retention_hours "
                "after the job finished, or with the upload it trained on)")
    if job.state is JobState.FAILED:
        return f"job {job.id} has no {name}: the job failed before the video was tracked ({job.error or 'no error'})"
    if job.state is JobState.CANCELLED:
        return f"job {job.id} has no {name}: the job was cancelled before the video was tracked"
    return f"job {job.id} has no {name}: the job {job.state.value} without writing {file}"
