"""The calls both clients make, described once (:class:`Call`: method, path, body, whether it may be retried, how
its answer is read) and run by each client's executor (sync or asyncio). :class:`Api` holds the calls whose shape
is the same in both clients: in :class:`~blendsplat_client.Client` they return values, in
:class:`~blendsplat_client.AsyncClient` awaitables of the same values."""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

from . import _pose
from ._config import IDEMPOTENT
from ._proto import render_pb2 as pb

CHUNK = 1 << 20
TERMINAL = frozenset({"succeeded", "failed", "cancelled"})
ARTEFACTS = ("report", "summary", "curves", "contact-sheet", "preview", "truth", "log", "overlay", "dataset",
             "track-report")


@dataclass
class Call:
    method: str
    path: str
    params: dict[str, Any] | None = None
    json: Any = None
    headers: dict[str, str] = field(default_factory=dict)
    body: Callable[[bool], Any] | None = None  # (asynchronous) -> content: a fresh body for every try
    read: str = "json"  # json | bytes | none | a key of the JSON answer
    timeout: float | None = None

    @property
    def idempotent(self) -> bool:
        return self.method in IDEMPOTENT or (self.method == "POST" and self.path == "/v1/jobs"
                                             and "Idempotency-Key" in self.headers)

    def result(self, status: int, content: bytes) -> Any:
        if self.read == "none" or status == 204:
            return None
        if self.read == "bytes":
            return content
        value = json.loads(content) if content else None
        return value if self.read == "json" else value[self.read]  # a list's key (avatars, adapters, uploads)


def part(name: str) -> str:
    """A path segment, quoted."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"not an id: {name!r}")
    return quote(name, safe="")


def _source(data: bytes | str | os.PathLike) -> tuple[Callable[[], Any], int, str]:
    """(opener of a binary file object, size, file name) of bytes or a path."""
    if isinstance(data, bytes | bytearray | memoryview):
        blob = bytes(data)
        import io

        return (lambda: io.BytesIO(blob)), len(blob), "data"
    path = Path(data)
    return (lambda: open(path, "rb")), path.stat().st_size, path.name


def file_body(data, progress: Callable[[int, int], None] | None, *, field_name: str | None = None,
              extra_parts: Mapping[str, tuple[bytes, str]] | None = None):
    """(headers, body factory): the file as the raw body, or as the multipart field ``field_name`` (after
    ``extra_parts``: name -> (bytes, content type)); read in 1 MiB pieces, ``progress(sent, total)`` after each, with
    its Content-Length (never chunked). A file that shrinks while it is sent raises OSError."""
    opener, size, filename = _source(data)
    head = tail = b""
    headers = {}
    if field_name is not None:
        boundary = f"blendsplat-{secrets.token_hex(12)}"
        name = filename.replace('"', "_").replace("\r", "_").replace("\n", "_")
        for key, (blob, kind) in (extra_parts or {}).items():
            head += (f'--{boundary}\r\nContent-Disposition: form-data; name="{key}"; filename="{key}"\r\n'
                     f"Content-Type: {kind}\r\n\r\n").encode() + blob + b"\r\n"
        head += (f'--{boundary}\r\nContent-Disposition: form-data; name="{field_name}"; filename="{name}"\r\n'
                 "Content-Type: application/octet-stream\r\n\r\n").encode()
        tail = f"\r\n--{boundary}--\r\n".encode()
        headers["Content-Type"] = f"multipart/form-data; boundary={boundary}"
    else:
        headers["Content-Type"] = "application/octet-stream"
    headers["Content-Length"] = str(len(head) + size + len(tail))

    def pieces():
        yield head
        sent = 0
        with opener() as f:
            while sent < size:  # exactly the Content-Length: a file that grew is sent as it was measured
                chunk = f.read(min(CHUNK, size - sent))
                if not chunk:
                    raise OSError(f"{filename} shrank while it was sent ({sent} of {size} bytes)")
                sent += len(chunk)
                yield chunk
                if progress is not None:
                    progress(sent, size)
        yield tail

    async def apieces():
        for piece in pieces():  # local reads of 1 MiB: short enough for the event loop
            yield piece

    return headers, (lambda asynchronous: apieces() if asynchronous else pieces())


class Api:
    """Calls of the same shape in both clients; ``_send(Call)`` and ``_rpc(name, request, idempotent)`` are each
    client's executors."""

    def _send(self, call: Call):  # pragma: no cover - each client's
        raise NotImplementedError

    def _rpc(self, name: str, request, idempotent: bool = True):  # pragma: no cover
        raise NotImplementedError

    # ------------------------------------------------------------------------------------------- avatars
    def list_avatars(self):
        """``GET /v1/avatars``: the avatars (dicts: id, loaded, gaussians, expression_names, joint_names, ...)."""
        return self._send(Call("GET", "/v1/avatars", read="avatars"))

    def get_avatar(self, avatar_id: str):
        return self._send(Call("GET", f"/v1/avatars/{part(avatar_id)}"))

    def put_avatar(self, avatar_id: str, bundle, progress=None):
        """``PUT /v1/avatars/{id}``: upload a bundle file (a path or bytes); the avatar."""
        headers, body = file_body(bundle, progress)
        return self._send(Call("PUT", f"/v1/avatars/{part(avatar_id)}", headers=headers, body=body,
                               timeout=max(self.timeout, 300.0)))

    def delete_avatar(self, avatar_id: str):
        return self._send(Call("DELETE", f"/v1/avatars/{part(avatar_id)}", read="none"))

    def load_avatar(self, avatar_id: str):
        return self._send(Call("POST", f"/v1/avatars/{part(avatar_id)}/load"))

    def unload_avatar(self, avatar_id: str):
        return self._send(Call("POST", f"/v1/avatars/{part(avatar_id)}/unload"))

    # ------------------------------------------------------------------------------------------- adapters
    def list_adapters(self):
        return self._send(Call("GET", "/v1/adapters", read="adapters"))

    def get_adapter(self, adapter_id: str):
        return self._send(Call("GET", f"/v1/adapters/{part(adapter_id)}"))

    def put_adapter(self, adapter_id: str, manifest, model, progress=None):
        """``PUT /v1/adapters/{id}``: the manifest (a dict, JSON bytes or a path) and the ONNX model (a path or
        bytes), multipart."""
        if isinstance(manifest, Mapping):
            manifest = json.dumps(manifest).encode()
        elif not isinstance(manifest, bytes | bytearray):
            manifest = Path(manifest).read_bytes()
        headers, body = file_body(model, progress, field_name="model",
                                  extra_parts={"manifest": (bytes(manifest), "application/json")})
        return self._send(Call("PUT", f"/v1/adapters/{part(adapter_id)}", headers=headers, body=body,
                               timeout=max(self.timeout, 120.0)))

    def delete_adapter(self, adapter_id: str):
        return self._send(Call("DELETE", f"/v1/adapters/{part(adapter_id)}"))

    # ------------------------------------------------------------------------------------------- uploads
    def upload(self, file, progress: Callable[[int, int], None] | None = None, *, timeout: float = 600.0):
        """``POST /v1/uploads``: a dataset archive (.tar.gz, .tar, .zip) or a video, streamed from disk as the
        multipart field ``file``; ``progress(sent, total)`` after each MiB. The upload (``upload_id``, ``kind``,
        ...). Not retried (not idempotent); ``timeout``: the server validates the whole dataset before it answers."""
        headers, body = file_body(file, progress, field_name="file")
        return self._send(Call("POST", "/v1/uploads", headers=headers, body=body, timeout=timeout))

    def list_uploads(self):
        return self._send(Call("GET", "/v1/uploads", read="uploads"))

    def get_upload(self, upload_id: str):
        return self._send(Call("GET", f"/v1/uploads/{part(upload_id)}"))

    def delete_upload(self, upload_id: str):
        return self._send(Call("DELETE", f"/v1/uploads/{part(upload_id)}", read="none"))

    # ------------------------------------------------------------------------------------------- jobs
    def submit_job(self, upload_id: str, *, idempotency_key: str | None = "auto", **spec):
        """``POST /v1/jobs``: train on an upload (``preset``, ``iterations``, ``avatar_id``, ``resolution``, ``seed``,
        ``webhook_url``, ...); the job. With an ``Idempotency-Key`` (a fresh one by default; None: none) a retried
        request returns the job the first one created, so the call is retried like an idempotent one."""
        headers = {}
        if idempotency_key:
            headers["Idempotency-Key"] = secrets.token_hex(16) if idempotency_key == "auto" else idempotency_key
        return self._send(Call("POST", "/v1/jobs", json={"upload_id": upload_id, **spec}, headers=headers))

    def jobs_page(self, state: str | None = None, limit: int = 50, cursor: str | None = None):
        """One page of ``GET /v1/jobs`` (newest first): ``{"jobs": [...], "next_cursor"}``."""
        params = {"limit": limit, **({"state": state} if state else {}), **({"cursor": cursor} if cursor else {})}
        return self._send(Call("GET", "/v1/jobs", params=params))

    def get_job(self, job_id: str):
        return self._send(Call("GET", f"/v1/jobs/{part(job_id)}"))

    def cancel_job(self, job_id: str):
        """``POST /v1/jobs/{id}/cancel``: the job (a running one stops before its next iteration)."""
        return self._send(Call("POST", f"/v1/jobs/{part(job_id)}/cancel"))

    def delete_job(self, job_id: str):
        return self._send(Call("DELETE", f"/v1/jobs/{part(job_id)}", read="none"))

    def artefact(self, job_id: str, name: str):
        """``GET /v1/jobs/{id}/artefacts/{name}``: its bytes (report, summary, curves, contact-sheet, ...)."""
        if name not in ARTEFACTS:
            raise ValueError(f"artefact must be one of {', '.join(ARTEFACTS)}, got {name!r}")
        return self._send(Call("GET", f"/v1/jobs/{part(job_id)}/artefacts/{name}", read="bytes",
                               timeout=max(self.timeout, 120.0)))

    # ------------------------------------------------------------------------------------------- gRPC
    def render(self, avatar: str, size=512, codec: str = "jpeg", *, quality: int = 0, expression=None,
               joints=None, eyelids=None, camera=None, background=None):
        """One frame, no session (gRPC ``Render``): a :class:`~blendsplat_client.Frame`."""
        width, height = (size, size) if isinstance(size, int) else size
        request = pb.RenderRequest(avatar_id=avatar, width=width, height=height, codec=_pose.codec(codec),
                                   quality=quality,
                                   frame=_pose.frame(1, expression, joints, eyelids, camera, background))
        return self._rpc("Render", request)
