"""Receive an upload (multipart form data or a raw body, chunked or not) straight to disk.

The size cap is enforced while reading: a declared Content-Length over the cap is refused before reading, and
a body (chunked or lying about its length) is cut off as soon as the file, or the whole body (form fields,
unnamed parts and anything after the closing boundary count too), passes the cap. A body that stalls for
``idle_timeout`` seconds or takes longer than ``timeout`` in all is cut off (408). The file is hashed (SHA-256)
while it is written, and its first bytes are kept for content sniffing.
"""

from __future__ import annotations

import asyncio
import hashlib
import re
import time
import unicodedata
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from anyio import to_thread
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import Request

MULTIPART_OVERHEAD_BYTES = 64 * 1024
"""Room for boundaries, part headers and small form fields on top of the file in a multipart body."""
HEAD_BYTES = 64
MAX_FIELD_BYTES = 4096
MAX_BOUNDARY_CHARS = 70
"""RFC 2046: a multipart boundary has 1 to 70 characters."""


class UploadError(Exception):
    """An upload that cannot be accepted; ``status`` is the HTTP status to answer with."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


@dataclass
class ReceivedFile:
    """A file written to ``path`` with its digest, size, first bytes, and the client's name for it."""

    path: Path
    sha256: str
    size: int
    head: bytes
    filename: str | None
    fields: dict[str, str] = field(default_factory=dict)


class _Sink:
    """Buffers, hashes, counts and writes file bytes; raises UploadError(413) past the cap."""

    def __init__(self, path: Path, max_bytes: int, chunk_bytes: int) -> None:
        self.path = path
        self.max_bytes = max_bytes
        self.chunk_bytes = chunk_bytes
        self.digest = hashlib.sha256()
        self.size = 0
        self.head = b""
        self.buffer = bytearray()
        self.fh: BinaryIO = open(path, "wb")  # noqa: SIM115 (closed in close())

    def add(self, data: bytes) -> None:
        if not data:
            return
        self.size += len(data)
        if self.size > self.max_bytes:
            raise UploadError(413, too_large(self.max_bytes))
        if len(self.head) < HEAD_BYTES:
            self.head += data[: HEAD_BYTES - len(self.head)]
        self.digest.update(data)
        self.buffer += data

    async def flush(self, force: bool = False) -> None:
        if self.buffer and (force or len(self.buffer) >= self.chunk_bytes):
            data = bytes(self.buffer)
            self.buffer.clear()
            await to_thread.run_sync(self.fh.write, data)

    def close(self) -> None:
        self.fh.close()


def too_large(max_bytes: int) -> str:
    return (f"the upload is larger than the limit of {max_bytes} bytes ({max_bytes / 2**20:.0f} MiB, setting "
            "RETARGET_API_MAX_UPLOAD_BYTES)")


_UNSAFE = frozenset(("Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"))
"""Unicode categories dropped from client names: controls, format characters (bidi overrides), surrogates,
private and unassigned code points, line and paragraph separators."""
MAX_FILENAME_CHARS = 255


def safe_text(text: str) -> str:
    """``text`` without unsafe characters (:data:`_UNSAFE`), spaces at its ends stripped."""
    return "".join(ch for ch in text if unicodedata.category(ch) not in _UNSAFE).strip()


def safe_filename(name: str | None) -> str | None:
    """The last part of a client-supplied file name, without control or format characters; None when nothing
    usable is left (empty, or only dots such as "." and "..", which name directories, not files)."""
    if not name:
        return None
    base = safe_text(re.split(r"[\\/]", name)[-1])[:MAX_FILENAME_CHARS].strip()
    return base if base.strip(". ") else None


async def bounded(stream: AsyncIterator[bytes], max_total: int, max_bytes: int, idle_timeout: float,
                  timeout: float) -> AsyncIterator[bytes]:
    """The chunks of ``stream``; UploadError 413 past ``max_total`` bytes in all, 408 when a chunk takes longer
    than ``idle_timeout`` or the whole body longer than ``timeout``."""
    deadline = time.monotonic() + timeout
    total = 0
    it = stream.__aiter__()
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise UploadError(408, f"the upload took longer than {timeout:.0f} s (setting "
                                   "RETARGET_API_UPLOAD_TIMEOUT_SECONDS)")
        try:
            chunk = await asyncio.wait_for(it.__anext__(), min(idle_timeout, left))
        except StopAsyncIteration:
            return
        except TimeoutError:
            raise UploadError(408, f"the upload sent nothing for {min(idle_timeout, left):.0f} s (setting "
                                   "RETARGET_API_UPLOAD_IDLE_TIMEOUT_SECONDS)") from None
        total += len(chunk)
        if total > max_total:
            raise UploadError(413, too_large(max_bytes))
        yield chunk


async def receive_upload(request: Request, dest: Path, max_bytes: int, chunk_bytes: int,
                         idle_timeout: float = 30.0, timeout: float = 600.0) -> ReceivedFile:
    """Read the request body into ``dest``; multipart needs a part named ``file``. Raises UploadError."""
    content_type = request.headers.get("content-type", "")
    is_multipart = content_type.lower().startswith("multipart/form-data")
    declared = request.headers.get("content-length")
    if declared is not None:
        try:
            length = int(declared)
        except ValueError as exc:
            raise UploadError(400, "Content-Length is not a number") from exc
        if length > max_bytes + (MULTIPART_OVERHEAD_BYTES if is_multipart else 0):
            raise UploadError(413, too_large(max_bytes))
    sink = _Sink(dest, max_bytes, chunk_bytes)
    stream = bounded(request.stream(), max_bytes + (MULTIPART_OVERHEAD_BYTES if is_multipart else 0), max_bytes,
                     idle_timeout, timeout)
    try:
        if is_multipart:
            filename, fields = await _receive_multipart(stream, content_type, sink)
        else:
            filename = safe_filename(request.query_params.get("filename") or request.headers.get("x-filename"))
            fields = {}
            async for chunk in stream:
                sink.add(chunk)
                await sink.flush()
        await sink.flush(force=True)
    except BaseException:
        sink.close()
        dest.unlink(missing_ok=True)
        raise
    sink.close()
    if sink.size == 0:
        dest.unlink(missing_ok=True)
        raise UploadError(400, "the upload is empty" if not is_multipart else
                          "no file in the form: send the file in a part named 'file'")
    return ReceivedFile(dest, sink.digest.hexdigest(), sink.size, sink.head, filename, fields)


async def _feed(parser: MultipartParser, stream: AsyncIterator[bytes], sink: _Sink) -> None:
    """Run the body through the parser; UploadError 400 when it is malformed."""
    try:
        async for chunk in stream:
            parser.write(chunk)
            await sink.flush()
        parser.finalize()
    except UploadError:
        raise
    except Exception as exc:  # python_multipart raises its own errors on malformed bodies
        raise UploadError(400, f"malformed multipart body: {exc}") from exc


async def _receive_multipart(
    stream: AsyncIterator[bytes], content_type: str, sink: _Sink
) -> tuple[str | None, dict[str, str]]:
    _, params = parse_options_header(content_type)
    boundary = params.get(b"boundary")
    if not boundary:
        raise UploadError(400, "multipart body without a boundary in Content-Type")
    if len(boundary) > MAX_BOUNDARY_CHARS:
        raise UploadError(400, f"the multipart boundary has {len(boundary)} characters; at most "
                               f"{MAX_BOUNDARY_CHARS} are allowed (RFC 2046)")

    state: dict[str, object] = {"headers": {}, "hname": b"", "hvalue": b"", "name": None, "is_file": False,
                                "data": bytearray()}
    fields: dict[str, str] = {}
    found: dict[str, object] = {"file": False, "filename": None}

    def on_part_begin() -> None:
        state.update(headers={}, hname=b"", hvalue=b"", name=None, is_file=False, data=bytearray())

    def on_header_field(data: bytes, start: int, end: int) -> None:
        state["hname"] = state["hname"] + data[start:end]  # type: ignore[operator]

    def on_header_value(data: bytes, start: int, end: int) -> None:
        state["hvalue"] = state["hvalue"] + data[start:end]  # type: ignore[operator]

    def on_header_end() -> None:
        state["headers"][bytes(state["hname"]).lower()] = bytes(state["hvalue"])  # type: ignore[index,call-overload]
        state["hname"] = b""
        state["hvalue"] = b""

    def on_headers_finished() -> None:
        disp = state["headers"].get(b"content-disposition", b"")  # type: ignore[attr-defined]
        _, opts = parse_options_header(disp)
        name = opts.get(b"name", b"").decode("utf-8", "replace")
        state["name"] = name
        if name == "file":
            if found["file"]:
                raise UploadError(400, "more than one part named 'file'")
            found["file"] = True
            found["filename"] = safe_filename(opts.get(b"filename", b"").decode("utf-8", "replace"))
            state["is_file"] = True

    def on_part_data(data: bytes, start: int, end: int) -> None:
        if state["is_file"]:
            sink.add(data[start:end])
        else:
            buf = state["data"]
            buf += data[start:end]  # type: ignore[operator]
            if len(buf) > MAX_FIELD_BYTES:
                raise UploadError(400, f"form field {state['name']!r} is longer than {MAX_FIELD_BYTES} bytes")

    def on_part_end() -> None:
        if not state["is_file"] and state["name"]:
            if len(fields) >= 20:
                raise UploadError(400, "too many form fields")
            fields[str(state["name"])] = bytes(state["data"]).decode("utf-8", "replace")  # type: ignore[call-overload]

    parser = MultipartParser(
        boundary,
        {
            "on_part_begin": on_part_begin,
            "on_part_data": on_part_data,
            "on_part_end": on_part_end,
            "on_header_field": on_header_field,
            "on_header_value": on_header_value,
            "on_header_end": on_header_end,
            "on_headers_finished": on_headers_finished,
        },
    )
    await _feed(parser, stream, sink)
    if not found["file"]:
        raise UploadError(400, "no file in the form: send the file in a part named 'file'")
    return found["filename"], fields  # type: ignore[return-value]
