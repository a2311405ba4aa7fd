"""Server-sent events (the WHATWG ``text/event-stream`` format) as ``GET /v1/jobs/{id}/events`` sends them."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from .errors import Unimplemented


@dataclass
class Event:
    """One job event: ``event`` (progress, state, preview, log; ``end`` closes a finished job's stream), its JSON
    ``data`` and ``id`` (resume after it)."""

    event: str
    data: dict[str, Any] = field(default_factory=dict)
    id: str | None = None


class Parser:
    """Feed lines; :meth:`line` returns an Event when a blank line dispatches one."""

    def __init__(self) -> None:
        self.kind, self.data, self.id = "message", [], None

    def line(self, raw: str) -> Event | None:
        line = raw.rstrip("\r")
        if not line:
            event = None
            if self.data:
                text = "\n".join(self.data)
                try:
                    value = json.loads(text)
                except ValueError:
                    value = {"text": text}
                event = Event(self.kind, value if isinstance(value, dict) else {"value": value}, self.id)
            self.kind, self.data = "message", []
            return event
        if line.startswith(":"):
            return None
        name, _, value = line.partition(":")
        value = value[1:] if value.startswith(" ") else value
        if name == "data":
            self.data.append(value)
        elif name == "event":
            self.kind = value or "message"
        elif name == "id" and "\0" not in value:
            self.id = value
        return None


def not_sse(headers) -> None:
    """Raise :class:`~blendsplat_client.errors.Unimplemented` unless an answer is an event stream."""
    kind = headers.get("content-type", "").split(";")[0].strip().lower()
    if kind != "text/event-stream":
        raise Unimplemented(f"the job event route answered {kind or 'no content type'}, not an event stream")
