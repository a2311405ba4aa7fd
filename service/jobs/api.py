"""The training jobs' REST routes (issue 15): dataset and video uploads, jobs, their artefacts, and real deletion.

Routes (mounted by :func:`service.http.app.create_app`; every answer is a pydantic model of
:mod:`service.jobs.schemas`, every error the one JSON error shape of :mod:`service.errors`)::

    POST   /v1/uploads                      multipart/form-data, an archive or a video in the field ``file``: 201
    GET    /v1/uploads                      every upload, oldest first
    GET    /v1/uploads/{id}
    DELETE /v1/uploads/{id}                 204; 409 while a queued or running job uses it
    POST   /v1/jobs                         JSON JobSpec (+ Idempotency-Key): 201 + Location, 200 on a replay
    GET    /v1/jobs?state=&limit=&cursor=   newest first, keyset pages: {jobs, next_cursor}
    GET    /v1/jobs/{id}
    POST   /v1/jobs/{id}/cancel             202 with the job (200 when it had already finished)
    GET    /v1/jobs/{id}/artefacts/{name}   report | summary | curves | contact-sheet | preview | truth | log
                                            | overlay | dataset | track-report (a job from a video)
    GET    /v1/jobs/{id}/events             server-sent events: the job's history, then live (service/jobs/events.py)
    DELETE /v1/jobs/{id}                    204: the row, its events and its work folder

The handlers are thin: :class:`~service.jobs.training.Training` (the app's ``state.training``) holds the stores and
the operations that span them, and states what deletion removes. **Uploads are streamed**: the body is parsed as it
arrives (:mod:`service.jobs.multipart`) and the file part's bytes go straight to
:meth:`~service.jobs.uploads.UploadStore.receive`, which writes them to disk, refuses more than
``settings.max_dataset_bytes`` (HTTP 413), checks and extracts the archive and validates the dataset (HTTP 422 with
the reason); a refused upload leaves nothing behind. A video (sniffed by its bytes: :mod:`service.jobs.video`) is
kept as it is, probed for the ``max_video_*`` limits without being decoded (HTTP 422 naming the limit), and tracked
by the job that trains on it (:mod:`service.jobs.track`).
"""

from __future__ import annotations

import functools
import logging
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, StreamingResponse
from starlette.requests import ClientDisconnect

from ..access.auth import Access
from ..access.http import Caller
from ..errors import BodyTooLarge, redact
from ..intake import declared_length
from ..openapi import ErrorBody
from . import events
from .archive import ArchiveError
from .artefacts import ARTEFACTS
from .checks import CURSOR_PATTERN, MAX_EVENT_ID
from .models import JobState
from .multipart import MULTIPART_SLACK, FilePart
from .schemas import JOB_ID_PATTERN, JobList, JobOut, JobSpec, UploadList, UploadOut
from .training import Training
from .uploads import ID_PATTERN as UPLOAD_ID_PATTERN
from .uploads import InvalidDataset
from .video import VideoError
from .webhooks import loggable_url

log = logging.getLogger(__name__)

MAX_PAGE = 500


# ------------------------------------------------------------------------------------------------------ routes
def _training(request: Request) -> Training:
    return request.app.state.training


_ERRORS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorBody, "description": "not found"},
    422: {"model": ErrorBody, "description": "invalid request (the field is named)"},
}
_IDEMPOTENCY = Annotated[str | None, Header(alias="Idempotency-Key", min_length=1, max_length=255,
                                            description="the same key and body return the same job (200)")]

JobId = Annotated[str, PathParam(pattern=JOB_ID_PATTERN.pattern, description="a job's id (POST /v1/jobs)")]
UploadId = Annotated[str, PathParam(pattern=UPLOAD_ID_PATTERN.pattern, description="an upload's id")]
ArtefactName = Annotated[Literal[tuple(ARTEFACTS)], PathParam(description="which artefact")]  # type: ignore

uploads = APIRouter(prefix="/v1/uploads", tags=["uploads"])
jobs = APIRouter(prefix="/v1/jobs", tags=["jobs"])


@uploads.post(
    "", status_code=201, response_model=UploadOut,
    summary="Upload a tracked-video dataset (an archive) or a video to track",
    description="multipart/form-data with the file in the field `file`: an archive (.tar.gz, .tar or .zip holding a "
                "dataset in the portable format, docs/tracked-video-format.md, at its root or in one top-level "
                "folder), or a video (MP4, MOV, WebM, MKV; recognised by its content, whatever its name) that the "
                "job trained on it tracks first. The body is streamed to disk; an archive is checked before "
                "anything is extracted and the dataset validated; a video is probed for the limits "
                "(BLENDSPLAT_MAX_VIDEO_SECONDS, _SIDE, _FRAMES) without being decoded and kept as it is. A refused "
                "upload leaves nothing behind.",
    responses={413: {"model": ErrorBody, "description": "larger than BLENDSPLAT_MAX_DATASET_BYTES"},
               422: {"model": ErrorBody, "description": "a hostile or corrupt archive (an extraction over "
                                                        "BLENDSPLAT_MAX_EXTRACTION_RATIO times the archive: reason "
                                                        "bomb), an invalid dataset, or a video over a limit, too "
                                                        "short or not decodable: the reason"}},
    openapi_extra={"requestBody": {"required": True, "content": {"multipart/form-data": {"schema": {
        "type": "object", "required": ["file"],
        "properties": {"file": {"type": "string", "format": "binary"}}}}}}})
async def create_upload(request: Request, response: Response, principal: Caller("jobs")) -> UploadOut:
    training = _training(request)
    limit = training.settings.max_dataset_bytes
    metrics = training.metrics
    try:
        declared = declared_length(request.headers)
        training.intake.check_declared(declared, limit + MULTIPART_SLACK, "file")  # the form's own bytes allowed
        await training.intake.admit(principal, declared)
        form = FilePart(request)
        await form.start()
        # The file part goes through the intake: spooled off the loop, then the tenant's quota on what arrived.
        spool = functools.partial(training.intake.receive, principal, limit=limit, field="file", admitted=True)
        # What it stores, extracted, before it is published: the tenant's quota and file bound (nothing kept if not)
        upload = await training.uploads.receive(form.chunks(), max_bytes=limit, filename=form.filename,
                                                tenant=principal.tenant, spool=spool,
                                                admit=functools.partial(training.admit_stored, principal))
    except (BodyTooLarge, ArchiveError, InvalidDataset, VideoError) as exc:
        if metrics is not None:
            kind = ("too_large" if isinstance(exc, BodyTooLarge) else "archive" if isinstance(exc, ArchiveError)
                    else "video" if isinstance(exc, VideoError) else "dataset")
            metrics.uploads.labels(kind).inc()
        raise
    except ClientDisconnect:
        log.info("upload: the client went away; nothing was kept")
        return Response(status_code=499)  # nobody reads it
    if metrics is not None:
        metrics.uploads.labels("accepted").inc()
        metrics.upload_bytes.inc(upload.size)
    response.headers["Location"] = f"/v1/uploads/{upload.id}"
    log.info("upload %s: %s of %d frames %dx%d (%s, %d bytes)", upload.id, upload.kind, upload.frames, upload.width,
             upload.height, upload.archive or upload.container, upload.size)
    return UploadOut.of(upload)


@uploads.get("", response_model=UploadList, summary="Uploaded datasets, oldest first")
def list_uploads(request: Request, principal: Caller("jobs")) -> UploadList:
    return UploadList(uploads=[UploadOut.of(u) for u in _training(request).uploads.list()
                               if principal.may_read(u.tenant)])


@uploads.get("/{upload_id}", response_model=UploadOut, summary="One upload", responses=_ERRORS)
def get_upload(upload_id: UploadId, request: Request, principal: Caller("jobs")) -> UploadOut:
    return UploadOut.of(_training(request).upload_for(upload_id, principal))


@uploads.delete("/{upload_id}", status_code=204, response_class=Response,
                summary="Delete an upload and the work folders of the finished jobs trained on it",
                description="Refused (409) while a queued or running job uses it: cancel or delete those first. "
                            "Finished jobs keep their rows; avatars trained from it stay.",
                responses={**_ERRORS, 409: {"model": ErrorBody, "description": "a queued or running job uses it"}})
def delete_upload(upload_id: UploadId, request: Request, principal: Caller("jobs")) -> Response:
    training = _training(request)
    training.upload_for(upload_id, principal)
    removed = training.delete_upload(upload_id)
    Access.audit(principal, "upload.delete", upload_id)
    log.info("upload %s deleted (and the work folders of jobs %s)", upload_id, removed)
    return Response(status_code=204)


@jobs.post("", status_code=201, response_model=JobOut, summary="Submit a training job",
           description="Queues a job that trains on an upload; a worker (`blendsplat worker`, or the one `blendsplat "
                       "up` runs) claims it. With an `Idempotency-Key` header a repeated request returns the job the "
                       "first one created (200); the same key with a different body is refused (409).",
           responses={200: {"model": JobOut, "description": "the job an earlier request with this key created"},
                      409: {"model": ErrorBody, "description": "the key was used with a different body"},
                      **_ERRORS})
def submit_job(body: JobSpec, request: Request, response: Response, principal: Caller("jobs"),
               idempotency_key: _IDEMPOTENCY = None) -> JobOut:
    training = _training(request)
    job, created = training.submit(body, idempotency_key, principal)
    response.status_code = 201 if created else 200
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    if created:
        shown = {**job.spec, "webhook_url": loggable_url(job.spec["webhook_url"])} if job.spec.get("webhook_url") \
            else job.spec  # the URL's path and query may hold tokens: never logged
        log.info("job %s submitted: %s", job.id, shown)
        Access.audit(principal, "job.submit", job.id, avatar=body.avatar_id, upload=body.upload_id)
    return training.job_out(job)


@jobs.get("", response_model=JobList, summary="Jobs, newest first, optionally of one state (keyset pages)",
          responses={422: _ERRORS[422]})
def list_jobs(request: Request, principal: Caller("jobs"), state: JobState | None = None,
              limit: Annotated[int, Query(ge=1, le=MAX_PAGE)] = 50,
              cursor: Annotated[str | None, Query(pattern=CURSOR_PATTERN.pattern, max_length=82,
                                                  description="next_cursor of the previous page")] = None) -> JobList:
    training = _training(request)
    page, next_cursor = training.jobs.list(state=state, limit=limit, cursor=cursor,
                                           tenant=None if principal.admin else principal.tenant)
    return JobList(jobs=[training.job_out(j) for j in page], next_cursor=next_cursor)


@jobs.get("/{job_id}", response_model=JobOut, summary="One job: state, progress, error, result, links",
          responses=_ERRORS)
def get_job(job_id: JobId, request: Request, principal: Caller("jobs")) -> JobOut:
    training = _training(request)
    return training.job_out(training.job_for(job_id, principal))


@jobs.post("/{job_id}/cancel", status_code=202, response_model=JobOut, summary="Cancel a job",
           description="A queued job is cancelled at once; a running one stops before its next iteration (its "
                       "worker checkpoints and ends it cancelled: watch its state). A finished job is left as it is "
                       "(200).",
           responses={200: {"model": JobOut, "description": "the job had already finished"}, **_ERRORS})
def cancel_job(job_id: JobId, request: Request, response: Response, principal: Caller("jobs")) -> JobOut:
    training = _training(request)
    job = training.job_for(job_id, principal)
    if job.finished:
        response.status_code = 200
    else:
        job = training.jobs.request_cancel(job_id)
        log.info("job %s: cancel requested (now %s)", job_id, job.state)
        Access.audit(principal, "job.cancel", job_id)
    return training.job_out(job)


@jobs.get("/{job_id}/artefacts/{name}", response_class=FileResponse,
          summary="A job's artefact: report, summary, curves, contact-sheet, preview, truth, log, overlay, dataset "
                  "or track-report",
          description="report (report.json: the held-out evaluation), summary (summary.json), curves (curves.png), "
                      "contact-sheet (contact_sheet.png), preview (preview.png: the latest, replaced as training "
                      "goes), truth (truth.png: the dataset's image of the preview's frame), log (log.jsonl). A job "
                      "from a video upload adds, once the video is tracked: overlay (overlay.png: the tracker's "
                      "detected and fitted points on a few frames), dataset (dataset.tar.gz: the tracked dataset, "
                      "which can be uploaded as it is) and track-report (track.json: frames kept, dropped and "
                      "interpolated, reprojection error). 404 with the reason while one is not written yet.",
          responses={200: {"content": {
              "application/json": {"schema": {"type": "object", "description": "report, summary or track-report"}},
              "image/png": {"schema": {"type": "string", "format": "binary"}},
              "application/gzip": {"schema": {"type": "string", "format": "binary",
                                              "description": "dataset: the tracked dataset (tar.gz)"}},
              "application/x-ndjson": {"schema": {"type": "string", "description": "one JSON event per line"}}}},
              404: _ERRORS[404]})
def get_artefact(job_id: JobId, name: ArtefactName, request: Request, principal: Caller("jobs")) -> Response:
    training = _training(request)
    training.job_for(job_id, principal)
    path, media_type = training.artefact(job_id, name)
    if media_type == "application/json":  # report, summary: the trainer records its paths; clients get none
        text = redact(path.read_text(encoding="utf-8", errors="replace"))
        return Response(text, media_type=media_type, headers={"Cache-Control": "no-store"})
    filename = f"{job_id}-{path.name}" if media_type == "application/gzip" else None  # a download (the dataset)
    return FileResponse(path, media_type=media_type, filename=filename, headers={"Cache-Control": "no-store"})


@jobs.get("/{job_id}/events", response_class=StreamingResponse,
          summary="The job's events as server-sent events: its history, then live, until it ends",
          description="text/event-stream; one event per recorded event: `id` (resume with the `Last-Event-ID` "
                      "header or `?after=`), `event` (progress, state, preview, log) and one line of JSON `data`. "
                      "A finished job's stream sends what is left and `event: end`, then closes. See "
                      "service/jobs/events.py.",
          responses={200: {"content": {"text/event-stream": {"schema": {
              "type": "string", "description": "id:, event:, data: lines (one JSON object) per event"}}}},
              429: {"model": ErrorBody, "description": "too many streams open"}, **_ERRORS})
def follow_job(job_id: JobId, request: Request, principal: Caller("jobs"),
               after: Annotated[int | None, Query(ge=0, le=MAX_EVENT_ID)] = None,
               last_event_id: Annotated[str | None, Header(alias="Last-Event-ID", max_length=64)] = None,
               ) -> StreamingResponse:
    training = _training(request)
    training.job_for(job_id, principal)  # NotFound: the one JSON 404, not a stream
    start = events.last_event_id(last_event_id, after)
    release = training.access.take_stream(principal)  # a key's streams
    try:
        return events.event_stream(request.app, training, job_id, start, on_close=release, key_id=principal.key_id)
    except BaseException:
        release()
        raise


@jobs.delete("/{job_id}", status_code=204, response_class=Response,
             summary="Delete a job: its row, events and work folder (a running one stops before its next iteration)",
             responses=_ERRORS)
def delete_job(job_id: JobId, request: Request, principal: Caller("jobs")) -> Response:
    training = _training(request)
    training.job_for(job_id, principal)
    training.delete_job(job_id)
    log.info("job %s deleted", job_id)
    Access.audit(principal, "job.delete", job_id)
    return Response(status_code=204)


ROUTERS = (uploads, jobs)
