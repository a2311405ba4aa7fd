"""A job's share of its tenant's storage quota (``tenant_storage_bytes``; :mod:`service.jobs.training` states the
whole rule).

- At submission, :func:`work_estimate`: the least the job's work folder will take, checked against the quota with
  the tenant's bundles, uploads and other work folders (the REST side, :meth:`Training.submit`).
- While it runs, :class:`WorkQuota`: the worker measures the work folder (checkpoints, previews, a resampled or
  tracked dataset, the overlay and the dataset archive of a video job, the trained bundle) at each checkpoint and at
  the end of each stage, records it on the job's row (``work_bytes``, what the REST side's quota checks sum), and
  fails the job with :class:`StorageQuotaExceeded` when its tenant now stores more than its quota. The measure at
  the end of an attempt (whatever ended it) is recorded without the check.

Admin keys' jobs (the admin tenant, or none when authentication is off) are recorded but never refused, as their
uploads are not.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from sqlalchemy.exc import SQLAlchemyError

from ..access.auth import ADMIN_TENANT
from ..errors import ResourceExhausted
from ..usage import BLOCK, Usage, tree_usage
from .models import Job

if TYPE_CHECKING:
    from .uploads import Upload
    from .worker import Worker

log = logging.getLogger("service.jobs.worker")  # the worker's log


class StorageQuotaExceeded(ResourceExhausted):
    """A running job's work folder took its tenant past ``tenant_storage_bytes``: the job fails with it (its error
    ``StorageQuotaExceeded: ...``)."""


def work_estimate(upload: Upload, resolution: int | None) -> int:
    """The least a job's work folder will take on disk, for the quota at submission: a block (its log), plus a
    video's tracked frames (at least the video's own bytes: frames as PNG are larger than the compressed stream),
    or a dataset resampled to a smaller ``resolution`` (its share of the dataset's bytes)."""
    least = BLOCK
    side = max(upload.width, upload.height)
    if upload.kind == "video":
        least += upload.usage.bytes
    elif resolution is not None and 0 < resolution < side:
        least += int(upload.usage.bytes * (resolution / side) ** 2)
    return least


class WorkQuota:
    """One job's work folder, measured, recorded and checked by the worker that runs it (module docstring)."""

    def __init__(self, worker: Worker, job: Job, workdir: Path):
        self.worker, self.job, self.workdir = worker, job, workdir
        settings = worker.settings
        self.exempt = settings.auth == "off" or job.tenant in (None, ADMIN_TENANT)

    def measure(self, check: bool = True) -> Usage:
        """Measure the work folder and record it on the job's row; with ``check``, StorageQuotaExceeded when the
        tenant's bundles, uploads and work folders together now pass its quota."""
        used = tree_usage(self.workdir)
        store = self.worker.store
        try:
            store.set_work_bytes(self.job.id, used.bytes)
        except (SQLAlchemyError, OSError) as exc:  # recorded at the next measure
            log.warning("job %s: could not record its work folder's size (%s)", self.job.id, type(exc).__name__)
            return used
        if check and not self.exempt:
            self._check(used)
        return used

    def _check(self, used: Usage) -> None:
        tenant, w = self.job.tenant, self.worker
        assert tenant is not None
        quota = w.settings.tenant_storage_bytes
        total = w.bundles.tenant_bytes(tenant) + w.uploads.tenant_bytes(tenant) + w.store.tenant_work_bytes(tenant)
        if total > quota:
            raise StorageQuotaExceeded(
                f"tenant {tenant!r} stores {total} bytes, past its quota of {quota} (tenant_storage_bytes): this "
                f"job's work folder takes {used.bytes}; delete avatars, uploads or jobs, then submit it again")
