"""The ``file`` part of a multipart/form-data upload body, parsed as it streams in (``POST /v1/uploads``).

python-multipart's streaming parser, not FastAPI's ``UploadFile`` (which spools the whole body first): the file
part's bytes are handed on as they arrive (:meth:`FilePart.chunks`, what
:meth:`~service.jobs.uploads.UploadStore.receive` writes to disk), never held whole; part headers and other form
fields are bounded.
"""

from __future__ import annotations

from collections.abc import AsyncIterator

from fastapi import Request
from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

from ..errors import InvalidArgument

MULTIPART_SLACK = 64 << 10  # multipart framing and small form fields allowed beyond the archive's size limit
_MAX_PART_HEADERS = 16 << 10  # bytes of part headers, all parts together
_MAX_OTHER_PARTS = 64 << 10  # bytes of form fields other than ``file``


class FilePart:
    """The ``file`` part of a multipart/form-data request body, parsed as the body arrives (bounded headers and
    other fields; the file's bytes are never held whole)."""

    FIELD = "file"

    def __init__(self, request: Request):
        kind, params = parse_options_header(request.headers.get("content-type", ""))
        boundary = params.get(b"boundary")
        if kind != b"multipart/form-data" or not boundary:
            raise InvalidArgument("expected a multipart/form-data body with the archive in the form field 'file'",
                                  field="file")
        self._body = request.stream().__aiter__()
        self._parser = MultipartParser(boundary, callbacks={
            "on_part_begin": self._part_begin, "on_part_data": self._part_data, "on_part_end": self._part_end,
            "on_header_field": self._header_field, "on_header_value": self._header_value,
            "on_header_end": self._header_end, "on_headers_finished": self._headers_finished,
            "on_end": self._end})
        self._name, self._value = bytearray(), bytearray()
        self._headers: dict[bytes, bytes] = {}
        self._header_bytes = self._other_bytes = 0
        self._in_file = self.found = self.done = self._ended = False
        self.filename: str | None = None
        self._out: list[bytes] = []

    # parser callbacks
    def _part_begin(self) -> None:
        self._headers, self._in_file = {}, False

    def _count_header(self, n: int) -> None:
        self._header_bytes += n
        if self._header_bytes > _MAX_PART_HEADERS:
            raise InvalidArgument("the multipart part headers are too long", field="file")

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self._count_header(end - start)
        self._name += data[start:end]

    def _header_value(self, data: bytes, start: int, end: int) -> None:
        self._count_header(end - start)
        self._value += data[start:end]

    def _header_end(self) -> None:
        self._headers[bytes(self._name).lower()] = bytes(self._value)
        self._name, self._value = bytearray(), bytearray()

    def _headers_finished(self) -> None:
        disposition, params = parse_options_header(self._headers.get(b"content-disposition", b""))
        if disposition == b"form-data" and params.get(b"name") == self.FIELD.encode() and not self.found:
            self._in_file = self.found = True
            raw = params.get(b"filename")
            self.filename = raw.decode("utf-8", "replace") if raw else None

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        if self._in_file:
            self._out.append(data[start:end])
            return
        self._other_bytes += end - start
        if self._other_bytes > _MAX_OTHER_PARTS:
            raise InvalidArgument("form fields other than 'file' are too large", field="body")

    def _part_end(self) -> None:
        if self._in_file:
            self._in_file, self.done = False, True

    def _end(self) -> None:
        self._ended = True

    # reading
    async def _feed(self) -> bool:
        """Parse the next piece of the body; False once the body has ended."""
        try:
            chunk = await self._body.__anext__()
        except StopAsyncIteration:
            return False
        if chunk:
            try:
                self._parser.write(chunk)
            except MultipartParseError as exc:
                raise InvalidArgument(f"not a valid multipart/form-data body ({exc})", field="body") from None
        return True

    async def start(self) -> None:
        """Read up to the start of the file part. InvalidArgument if the body has none."""
        while not self.found:
            if not await self._feed():
                raise InvalidArgument("the body has no form field 'file' (the dataset archive)", field="file")

    async def chunks(self) -> AsyncIterator[bytes]:
        """The file part's bytes as they arrive; the rest of the (bounded) body is read after it."""
        while True:
            if self._out:
                data = b"".join(self._out)
                self._out.clear()
                yield data
            if self.done:
                break
            if not await self._feed():
                raise InvalidArgument("the body ended inside the file part (a truncated upload)", field="file")
        while not self._ended and await self._feed():  # the closing boundary and any small trailing fields
            pass
