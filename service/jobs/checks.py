"""The job store's input checks and encodings: canonical JSON, progress reports, states, leases, page cursors.

Every value a caller hands :class:`~service.jobs.store.JobStore` passes one of these before it reaches a row, so a
bad one is an InvalidArgument naming its field and never a database error.
"""

from __future__ import annotations

import json
import math
import numbers
import re
import secrets
from collections.abc import Mapping
from datetime import UTC, datetime, timedelta
from typing import Any

from ..errors import InvalidArgument
from .models import JobRecord, JobState

MAX_LIST = 500  # the most jobs, events or deliveries one call returns
MAX_EVENT_ID = 2**63 - 1  # event ids are PostgreSQL bigints: a cursor past this is refused, never queried
PROGRESS_FIELDS: dict[str, type] = {
    "iteration": int, "total_iterations": int, "gaussians": int,
    "fraction": float, "eta_seconds": float, "loss": float, "psnr": float,
}


def new_job_id() -> str:
    return "job_" + secrets.token_urlsafe(15)  # 20 url-safe characters, 120 random bits


def utcnow() -> datetime:
    return datetime.now(UTC)


def canonical(value: Any, field: str) -> str:
    """``value`` as canonical JSON (sorted keys, no NaN); InvalidArgument naming ``field`` if it has none."""
    try:
        return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise InvalidArgument(f"not JSON-serialisable ({exc})", field=field) from None


def json_object(value: Any, field: str) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise InvalidArgument(f"expected a JSON object, got {type(value).__name__}", field=field)
    return json.loads(canonical(dict(value), field))


def progress_report(progress: Mapping[str, Any]) -> dict[str, Any]:
    """A progress report checked: the known fields (:data:`PROGRESS_FIELDS`) are numbers or None (a non-finite
    float, a diverged loss say, becomes None); other keys are kept for the event if they are JSON."""
    if not isinstance(progress, Mapping):
        raise InvalidArgument(f"expected a mapping, got {type(progress).__name__}", field="progress")
    out: dict[str, Any] = {}
    for key, value in progress.items():
        kind = PROGRESS_FIELDS.get(key)
        if kind is not None and value is not None:
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise InvalidArgument(f"expected a number, got {value!r}", field=f"progress.{key}")
            if kind is int:
                if not (isinstance(value, numbers.Integral) or float(value).is_integer()):
                    raise InvalidArgument(f"expected an integer, got {value!r}", field=f"progress.{key}")
                value = int(value)
            else:
                value = float(value) if math.isfinite(float(value)) else None
        out[key] = value
    return json.loads(canonical(out, "progress"))


def job_state(value: JobState | str, field: str = "state") -> JobState:
    try:
        return JobState(value)
    except ValueError:
        raise InvalidArgument(f"{value!r} is not a job state ({', '.join(JobState)})", field=field) from None


def check_lease(worker_id: str, lease_seconds: float) -> timedelta:
    """A worker's lease request checked: a worker id of 1 to 255 characters and a positive duration."""
    if not (isinstance(worker_id, str) and 0 < len(worker_id) <= 255):
        raise InvalidArgument("a worker id is 1 to 255 characters", field="worker_id")
    if isinstance(lease_seconds, bool) or not isinstance(lease_seconds, numbers.Real) or not lease_seconds > 0:
        raise InvalidArgument(f"a positive number of seconds, got {lease_seconds!r}", field="lease_seconds")
    return timedelta(seconds=float(lease_seconds))


# A page cursor is the keyset position of the last job listed: its creation time in microseconds since the epoch
# and its id. Every string of this form is a position (a page that may be empty), so the API can state the pattern.
CURSOR_PATTERN = re.compile(r"^([0-9]{1,16})~([A-Za-z0-9_-]{1,64})$")
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


def encode_cursor(record: JobRecord) -> str:
    return f"{(record.created_at - _EPOCH) // timedelta(microseconds=1)}~{record.id}"


def decode_cursor(cursor: str) -> tuple[datetime, str]:
    match = CURSOR_PATTERN.match(cursor)
    if match is None:
        raise InvalidArgument("not a cursor this listing returned (<microseconds>~<job id>)", field="cursor")
    return _EPOCH + timedelta(microseconds=int(match[1])), match[2]


def event_cursor(value: int | str, field: str) -> int:
    """An event cursor (``Last-Event-ID``, ``?after=``) checked: an integer from 0 to :data:`MAX_EVENT_ID`, else
    InvalidArgument naming ``field`` (a value past a bigint would fail in the database mid-stream)."""
    text = str(value).strip()
    if not (text.isascii() and text.isdigit() and len(text) <= 20) or int(text) > MAX_EVENT_ID:
        raise InvalidArgument(f"must be an event id (an integer from 0 to {MAX_EVENT_ID}) this stream sent",
                              field=field)
    return int(text)
