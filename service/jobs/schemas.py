"""What the training jobs' REST API reads and answers (pydantic models), and :class:`JobSpec`, the one job spec.

:class:`JobSpec` is the body of ``POST /v1/jobs``, the ``spec`` a job row stores (its :meth:`JobSpec.stored`
form) and what the worker trains: the API validates a request with it and the worker validates the stored spec
with it again (:meth:`JobSpec.parse`), so both sides hold one set of fields and bounds. Specs stored by earlier
versions (the same fields; ``checkpoint_every``, ``gaussians``, ``mouth`` only when given) validate unchanged.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping
from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_serializer

from ..errors import InvalidArgument
from ..store import ID_PATTERN as AVATAR_ID_PATTERN
from .models import JobState
from .uploads import ID_PATTERN as UPLOAD_ID_PATTERN
from .uploads import Upload
from .webhooks import MAX_URL_CHARS as MAX_WEBHOOK_URL
from .webhooks import check_url as check_webhook_url

log = logging.getLogger(__name__)

# http(s)://host[:port][/path...]: no credentials, no whitespace (webhooks.check_url checks the rest)
WEBHOOK_URL_PATTERN = (r"^https?://[A-Za-z0-9][A-Za-z0-9.-]{0,252}(:([1-9][0-9]{0,3}|[1-5][0-9]{4}|6[0-4][0-9]{3}|"
                       r"65[0-4][0-9]{2}|655[0-2][0-9]|6553[0-5]))?(/[!-~]*)?$")
JOB_ID_PATTERN = re.compile(r"^job_[A-Za-z0-9_-]{1,60}$")
MAX_ITERATIONS = 1_000_000
MAX_GAUSSIANS = 200_000  # initial face Gaussians (the presets' densification cap, max_gaussians)
MAX_MOUTH = 50_000  # initial mouth-interior Gaussians
_OMITTED_WHEN_UNSET = ("webhook_url", "checkpoint_every", "gaussians", "mouth")  # stored only when given


# ------------------------------------------------------------------------------------------------------ the spec
class JobSpec(BaseModel):
    """A training job: train ``preset`` on an upload and commit the avatar to the bundle store as ``avatar_id``
    (replacing an avatar of that id, as ``PUT /v1/avatars/{id}`` does). Integers are JSON integers (no strings,
    booleans or fractions)."""

    model_config = ConfigDict(extra="forbid", frozen=True, json_schema_extra={"examples": [
        {"upload_id": "upl_0123456789abcdefghij", "preset": "tiny", "avatar_id": "ada"}]})

    upload_id: str = Field(pattern=UPLOAD_ID_PATTERN.pattern, description="an upload's id (POST /v1/uploads)")
    preset: Literal["tiny", "paper"] = Field("tiny", description="tiny: minutes on a CPU; paper: the paper's "
                                                                 "40k iterations")
    iterations: int | None = Field(None, ge=1, le=MAX_ITERATIONS, strict=True, description="default: the preset's")
    avatar_id: str = Field(pattern=AVATAR_ID_PATTERN.pattern, max_length=128,
                           description="the id the trained avatar gets in the bundle store")
    resolution: int | None = Field(
        None, ge=16, le=8192, strict=True,
        description="longest image side to train at: a larger dataset is resampled (frames and masks filtered, "
                    "intrinsics scaled) to it, keeping its aspect ratio; a dataset no larger trains at its own size. "
                    "Default: the dataset's own size. A video upload is tracked at this size (a square head crop), "
                    "default its short side, at most 512")
    seed: int = Field(0, ge=0, le=2**32 - 1, strict=True, description="initialisation and frame-sampling seed")
    webhook_url: str | None = Field(None, min_length=8, max_length=MAX_WEBHOOK_URL, pattern=WEBHOOK_URL_PATTERN,
                                    description="http(s) URL that gets a signed POST on every state change of the job "
                                                "(service/jobs/webhooks.py); left out of the spec when not given")
    checkpoint_every: int | None = Field(
        None, ge=1, le=MAX_ITERATIONS, strict=True,
        description="iterations between checkpoints (and previews); default: the preset's. A fresh start only: a "
                    "resumed job keeps its checkpoint's")
    gaussians: int | None = Field(None, ge=1, le=MAX_GAUSSIANS, strict=True,
                                  description="initial face Gaussians; default: the preset's (a fresh start only)")
    mouth: int | None = Field(None, ge=1, le=MAX_MOUTH, strict=True,
                              description="initial mouth-interior Gaussians; default: the preset's (a fresh start "
                                          "only)")

    @field_validator("avatar_id")
    @classmethod
    def _avatar_id(cls, value: str) -> str:
        if value.endswith(".tmp"):
            raise ValueError("an avatar id may not end in '.tmp'")
        return value

    @field_validator("webhook_url")
    @classmethod
    def _webhook_url(cls, value: str | None) -> str | None:
        return None if value is None else check_webhook_url(value)

    @model_serializer(mode="wrap")
    def _without_unset_options(self, handler):
        out = handler(self)
        for name in _OMITTED_WHEN_UNSET:
            if out.get(name) is None:
                out.pop(name, None)
        return out

    def stored(self) -> dict[str, Any]:
        """The spec as a job row keeps it (and as its idempotency hash covers it): every field, except the
        optional ones that were not given."""
        return self.model_dump()

    @classmethod
    def parse(cls, spec: Mapping[str, Any]) -> JobSpec:
        """A stored spec validated again (the worker, before it trains): InvalidArgument naming the first bad key
        (``spec.<key>``). Keys this version does not know (a newer API's, during a rolling update) are ignored and
        logged, not refused."""
        if not isinstance(spec, Mapping):
            raise InvalidArgument(f"expected a JSON object, got {type(spec).__name__}", field="spec")
        unknown = sorted(set(spec) - set(cls.model_fields))
        if unknown:
            log.info("job spec: ignoring unknown keys %s", unknown)
        try:
            return cls.model_validate({k: v for k, v in spec.items() if k in cls.model_fields})
        except ValidationError as exc:
            error = exc.errors()[0]
            where = ".".join(str(part) for part in error["loc"])
            got = "" if error["type"] == "missing" else f" (got {repr(error.get('input'))[:80]})"
            raise InvalidArgument(error["msg"] + got, field=f"spec.{where}" if where else "spec") from None

    def preset_overrides(self) -> dict[str, int]:
        """The preset fields this spec overrides (for a fresh start)."""
        names = ("checkpoint_every", "gaussians", "mouth")
        return {k: getattr(self, k) for k in names if getattr(self, k) is not None}


# ------------------------------------------------------------------------------------------------------ uploads
class UploadLinks(BaseModel):
    self: str
    jobs: str = Field(description="where to POST a job that trains on this upload")


class UploadOut(BaseModel):
    upload_id: str
    kind: Literal["dataset", "video"] = Field(
        "dataset", description="dataset: a tracked-video dataset (an archive, extracted); video: a video kept as it "
                               "is, tracked by the job that trains on it")
    size: int = Field(description="bytes of the file as received (an archive itself is not kept; a video is)")
    sha256: str = Field(description="of the file as received")
    frames: int
    width: int = Field(description="a video's: as displayed (its rotation applied)")
    height: int
    face_model: str = Field(description="the face model the video was (a video's: will be) tracked with")
    filename: str | None = Field(None, description="the client's file name (display only)")
    archive: str | None = Field(description="tar, tar.gz or zip; null for a video")
    container: str | None = Field(None, description="a video's: mp4, mov, webm or mkv (null for a dataset)")
    duration: float | None = Field(None, description="a video's length in seconds (null for a dataset)")
    fps: float | None = Field(None, description="a video's frame rate (null for a dataset)")
    created_at: datetime
    links: UploadLinks

    @classmethod
    def of(cls, upload: Upload) -> UploadOut:
        return cls(upload_id=upload.id, kind="video" if upload.kind == "video" else "dataset", size=upload.size,
                   sha256=upload.sha256, frames=upload.frames, width=upload.width, height=upload.height,
                   face_model=upload.face_model, filename=upload.filename, archive=upload.archive,
                   container=upload.container, duration=upload.duration, fps=upload.fps,
                   created_at=upload.created_at, links=UploadLinks(self=f"/v1/uploads/{upload.id}", jobs="/v1/jobs"))


class UploadList(BaseModel):
    uploads: list[UploadOut]


# --------------------------------------------------------------------------------------------------------- jobs
class WebhookOut(BaseModel):
    id: str = Field(description="the message id (the webhook-id header), the same on every attempt")
    event: str = Field(description="job.running, job.succeeded, job.failed, job.cancelled or job.queued (requeued)")
    status: Literal["pending", "delivered", "failed"]
    attempts: int
    last_status: int | None = Field(description="the HTTP status of the last answer")
    last_error: str | None
    next_attempt_at: datetime | None
    created_at: datetime
    delivered_at: datetime | None


class Progress(BaseModel):
    fraction: float | None = Field(None, description="0 to 1 (of training; null while a video is tracked)")
    iteration: int | None = None
    total_iterations: int | None = None
    eta_seconds: float | None = None
    loss: float | None = None
    psnr: float | None = None
    gaussians: int | None = None


class JobLinks(BaseModel):
    self: str
    cancel: str
    upload: str | None = None
    artefacts: dict[str, str] = Field(description="the artefacts written so far, by name")
    avatar: str | None = Field(None, description="the trained avatar (when the job succeeded)")


class JobOut(BaseModel):
    id: str
    state: JobState
    spec: dict[str, Any] = Field(description="the job's request (JobSpec's fields)")
    attempts: int
    max_attempts: int
    cancel_requested: bool
    progress: Progress
    error: str | None
    result: dict[str, Any] | None = Field(description="on success: avatar_id, digest, evaluation, final_psnr, "
                                                      "iterations, seconds")
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime
    links: JobLinks
    webhooks: list[WebhookOut] = Field([], description="the deliveries of the job's webhook_url, oldest first")


class JobList(BaseModel):
    jobs: list[JobOut]
    next_cursor: str | None = Field(description="pass as ?cursor= for the next page; null on the last")
