"""The training-jobs wing: a durable job queue (SQLAlchemy 2 on the shared database of :mod:`service.db`), the REST
routes of uploads and jobs, the worker that trains them, job events and webhooks, and the command-line client.

The jobs table is the single source of truth: no broker holds a job. :class:`JobStore` is the one API of the queue
(submit, claim, heartbeat, finish, release, cancel, sweep, events); ``store.py`` states the contract. The modules:

- the queue: ``models.py`` (tables, values), ``store.py`` (JobStore) with ``queries.py`` (reads), ``outbox.py``
  (webhook deliveries), ``wakeup.py`` (waking workers), ``checks.py`` (input checks, cursors);
- the API: ``schemas.py`` (JobSpec, the one job spec, and the response models), ``training.py`` (Training: the
  stores and what spans them), ``api.py`` (the routes), ``multipart.py`` (the streamed upload body),
  ``events.py`` (server-sent events);
- uploads: ``uploads.py`` (UploadStore), ``archive.py`` with ``archive_readers.py`` (checked extraction),
  ``video.py`` (a video upload: sniffed, probed for the limits);
- training: ``worker.py`` (``blendsplat worker``), ``run.py`` (one job trained to its end), ``attempt.py`` (its
  lease: heartbeats, cancel), ``artefacts.py`` (the work folder's files, the commit), ``resize.py`` (a dataset at
  the job's resolution), ``track.py`` (a video upload's track stage);
- ``webhooks.py`` (the dispatcher); ``cli.py`` with ``display.py`` (``blendsplat jobs``, over the
  blendsplat_client package in clients/python).
"""

from .checks import PROGRESS_FIELDS, new_job_id
from .models import TERMINAL, EventKind, HeartbeatReply, Job, JobEvent, JobState
from .store import IdempotencyConflict, JobStore
from .wakeup import CHANNEL

__all__ = [
    "CHANNEL", "PROGRESS_FIELDS", "TERMINAL", "EventKind", "HeartbeatReply", "IdempotencyConflict", "Job", "JobEvent",
    "JobState", "JobStore", "new_job_id",
]
