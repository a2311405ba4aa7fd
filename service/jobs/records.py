"""The upload record (``upload.json``: :class:`Upload`), upload ids, and the refusal of a dataset that is not valid
(:class:`InvalidDataset`); the store that writes and reads them is :mod:`service.jobs.uploads`."""

from __future__ import annotations

import json
import os
import re
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path

from ..errors import InvalidArgument
from ..usage import Usage

ID_PATTERN = re.compile(r"^upl_[A-Za-z0-9_-]{16,64}$")
RECORD = "upload.json"
DATASET = "dataset"
VIDEO = "video"  # a video upload's file: video.<container>
KINDS = ("dataset", "video")
_MAX_PROBLEMS = 50  # problems kept in an InvalidDataset
_MAX_PROBLEM_CHARS = 300  # each
_MAX_MESSAGE_CHARS = 4000
_MAX_FILENAME_CHARS = 255


class InvalidDataset(InvalidArgument):
    """The archive was well formed but the dataset in it is not valid. ``problems`` lists them (``"field or file:
    message"``, as ``blendsplat data validate`` prints them; at most 50, each bounded); the message names them
    all up to a bounded length. ``field`` is ``"file"``."""

    def __init__(self, problems: list[str]):
        self.count = len(problems)
        self.problems = [_clip(p, _MAX_PROBLEM_CHARS) for p in problems[:_MAX_PROBLEMS]]
        text = f"the dataset is not valid ({self.count} problem{'s' if self.count != 1 else ''}): "
        shown = 0
        for p in self.problems:
            if len(text) + len(p) + 2 > _MAX_MESSAGE_CHARS:
                break
            text += ("; " if shown else "") + p
            shown += 1
        if shown < self.count:
            text += f"; ... and {self.count - shown} more"
        super().__init__(text, field="file")


@dataclass(frozen=True)
class Upload:
    """What the store records about a published upload (``upload.json``)."""

    id: str
    created_at: datetime  # UTC
    size: int  # bytes of the archive as received
    sha256: str  # of the archive as received
    frames: int
    width: int
    height: int
    face_model: str
    filename: str | None  # the client's file name (display only: never used as a path)
    archive: str | None  # "tar", "tar.gz" or "zip"; None for a video
    tenant: str | None = None  # the owning tenant (service/access/auth.py; None: admin keys only)
    kind: str = "dataset"  # "dataset" (an archive, extracted) or "video" (kept as the file, tracked by its job)
    container: str | None = None  # a video's: "mp4", "mov", "webm" or "mkv"
    duration: float | None = None  # a video's seconds
    fps: float | None = None  # a video's frame rate
    stored_bytes: int | None = None  # what it takes on disk (service/usage.py); None: recorded before it was measured
    files: int | None = None  # its entries on disk (files and folders)

    def to_json(self) -> dict:
        """The JSON object of ``upload.json`` (``created_at`` as ISO 8601 UTC; a dataset's record as before videos:
        without ``kind`` and the video fields)."""
        out = asdict(self)
        out["created_at"] = self.created_at.isoformat().replace("+00:00", "Z")
        if self.kind == "dataset":
            for key in ("kind", "container", "duration", "fps"):
                out.pop(key)
        return out

    @classmethod
    def from_json(cls, data: dict) -> Upload:
        created = datetime.fromisoformat(data["created_at"].replace("Z", "+00:00"))
        return cls(id=str(data["id"]), created_at=created, size=int(data["size"]), sha256=str(data["sha256"]),
                   frames=int(data["frames"]), width=int(data["width"]), height=int(data["height"]),
                   face_model=str(data["face_model"]), filename=data.get("filename"),
                   archive=data["archive"] if isinstance(data.get("archive"), str) else None,
                   tenant=data["tenant"] if isinstance(data.get("tenant"), str) else None,
                   kind=str(data.get("kind") or "dataset"), container=data.get("container"),
                   duration=_number(data.get("duration")), fps=_number(data.get("fps")),
                   stored_bytes=_count(data.get("stored_bytes")), files=_count(data.get("files")))

    @property
    def usage(self) -> Usage:
        """What it takes on disk (a record from before the measure: its size as received, two entries)."""
        return Usage(self.stored_bytes if self.stored_bytes is not None else self.size,
                     self.files if self.files is not None else 2)


def check_upload_id(upload_id: str, field: str = "upload_id") -> str:
    """``upload_id`` if it is an upload id (``upl_`` then 16 to 64 of ``A-Z a-z 0-9 _ -``), else InvalidArgument."""
    if not isinstance(upload_id, str) or not ID_PATTERN.match(upload_id):
        raise InvalidArgument(f"{str(upload_id)[:80]!r} is not an upload id ('upl_' followed by 16 to 64 letters, "
                              "digits, '_' or '-')", field=field)
    return upload_id


def _count(value) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 0 else None


def _number(value) -> float | None:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def _clip(text: str, limit: int) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def display_name(filename: str | None) -> str | None:
    """The client's file name for display: its last path component, printable characters only, bounded."""
    if not filename:
        return None
    base = re.split(r"[/\\]", str(filename))[-1]
    base = "".join(c for c in base if c.isprintable())
    return _clip(base, _MAX_FILENAME_CHARS) or None


def write_record(path: Path, upload: Upload) -> None:
    with open(path, "w", encoding="utf-8") as f:
        json.dump(upload.to_json(), f, indent=2)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.chmod(path, 0o644)
