"""Server-sent events as a client reads them (the WHATWG ``text/event-stream`` format): what
``GET /v1/jobs/{id}/events`` (:mod:`service.jobs.events`) sends, parsed line by line into :class:`Event`.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any


@dataclass
class Event:
    """One server-sent event: ``id``, ``event`` (progress, state, preview, log; ``end`` closes a finished job's
    stream) and its JSON ``data``."""

    event: str
    data: dict[str, Any] = field(default_factory=dict)
    id: str | None = None


def parse_events(lines: Iterator[str]) -> Iterator[Event]:
    """Server-sent events from the stream's lines (the WHATWG event-stream format): ``id:``, ``event:``,
    ``data:`` (lines joined; one JSON object here), comments and ``retry:`` skipped; a blank line dispatches."""
    kind, data, event_id = "message", [], None
    for raw in lines:
        line = raw.rstrip("\r")
        if not line:
            if data:
                text = "\n".join(data)
                try:
                    value = json.loads(text)
                except ValueError:
                    value = {"text": text}
                yield Event(kind, value if isinstance(value, dict) else {"value": value}, event_id)
            kind, data = "message", []
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        value = value[1:] if value.startswith(" ") else value
        if name == "data":
            data.append(value)
        elif name == "event":
            kind = value or "message"
        elif name == "id" and "\0" not in value:
            event_id = value  # the last event id persists until another one replaces it
