"""Bounded access to a parsed glTF 2.0 document: typed JSON getters, embedded buffers and images, and accessor
decoding with numpy (every componentType, normalized integers, byteStride, sparse accessors, padded matrices).

Nothing here trusts the file: every index is range-checked, every byte range is checked against the real buffer
length before a view is made, element counts are checked against ``max_accessor_elements`` before anything is
allocated, and accessor ``min``/``max`` are ignored. Only ``data:`` URIs are resolved; any other URI is an error
and no other file is ever opened.
"""

from __future__ import annotations

import base64
import binascii
import math
import os
import urllib.parse
from typing import Any

import numpy as np

from retarget_core.errors import InvalidFileError, LimitExceededError, UnsupportedFileError

COMPONENT_DTYPES: dict[int, np.dtype] = {
    5120: np.dtype("<i1"),  # BYTE
    5121: np.dtype("<u1"),  # UNSIGNED_BYTE
    5122: np.dtype("<i2"),  # SHORT
    5123: np.dtype("<u2"),  # UNSIGNED_SHORT
    5125: np.dtype("<u4"),  # UNSIGNED_INT
    5126: np.dtype("<f4"),  # FLOAT
}
# Accessor type -> (columns, rows); vectors and scalars are one column.
TYPE_SHAPES: dict[str, tuple[int, int]] = {
    "SCALAR": (1, 1), "VEC2": (1, 2), "VEC3": (1, 3), "VEC4": (1, 4), "MAT2": (2, 2), "MAT3": (3, 3), "MAT4": (4, 4),
}  # fmt: skip
SPARSE_INDEX_TYPES = (5121, 5123, 5125)

PARSE_BUDGET_ENV = "RETARGET_PARSE_BUDGET_BYTES"
DEFAULT_PARSE_BUDGET_BYTES = 300 * 1024 * 1024
"""Memory one parse may allocate for decoded data (the service sets it from its own setting)."""
MAX_PERCENT_ENCODED_URI_CHARS = 1024 * 1024
"""Longest percent-encoded (not base64) data: URI: decoding those is slow and memory-hungry; use base64."""
DECODED_BYTES_PER_VALUE = 16
"""What one decoded accessor value costs: the decoded copy and the float64 arrays made from it."""


def parse_budget_bytes() -> int:
    """The parse budget in bytes (environment ``RETARGET_PARSE_BUDGET_BYTES``, default 300 MiB)."""
    try:
        return max(1, int(os.environ.get(PARSE_BUDGET_ENV, DEFAULT_PARSE_BUDGET_BYTES)))
    except ValueError:
        return DEFAULT_PARSE_BUDGET_BYTES


class ParseBudget:
    """Counts what a parse is about to allocate and refuses it, before allocating, past the budget."""

    def __init__(self, label: str | None, total: int | None = None) -> None:
        self.total = parse_budget_bytes() if total is None else total
        self.used = 0
        self.label = label

    def charge(self, nbytes: int, what: str) -> None:
        """Account for ``nbytes``; LimitExceededError naming ``what`` when the budget would be passed."""
        if self.used + nbytes > self.total:
            raise LimitExceededError(
                f"{what} needs about {max(1, nbytes >> 20)} MiB of memory; with what the file needed before, that "
                f"is over the parse budget of {self.total >> 20} MiB (setting RETARGET_PARSE_BUDGET_BYTES)",
                self.label,
            )
        self.used += nbytes


def _align4(n: int) -> int:
    return (n + 3) & ~3


def decode_data_uri(uri: str, what: str, label: str | None) -> tuple[bytes, str | None]:
    """Bytes and MIME type of a ``data:`` URI; raises InvalidFileError for any other URI (never opens a file)."""
    if not uri.startswith("data:"):
        shown = uri if len(uri) <= 200 else uri[:200] + "..."
        raise InvalidFileError(
            f"{what} refers to the external resource {shown!r}: only self-contained files (GLB or data: URIs) are accepted",
            label,
        )
    head, sep, payload = uri[5:].partition(",")
    if not sep:
        raise InvalidFileError(f"{what} has a malformed data: URI (no comma)", label)
    params = head.split(";")
    mime = params[0] or None
    try:
        if "base64" in params[1:]:
            data = base64.b64decode(payload, validate=False)
        else:
            if len(payload) > MAX_PERCENT_ENCODED_URI_CHARS:
                raise LimitExceededError(
                    f"{what} has a percent-encoded data: URI of {len(payload)} characters, over the limit of "
                    f"{MAX_PERCENT_ENCODED_URI_CHARS}; embed large buffers as base64 or use GLB", label)
            data = urllib.parse.unquote_to_bytes(payload)
    except (binascii.Error, ValueError) as exc:
        raise InvalidFileError(f"{what} has a data: URI that is not valid base64 ({exc})", label) from exc
    return data, mime


class GltfData:
    """A glTF JSON document together with its resolved binary buffers.

    doc: the parsed JSON object.
    buffers: one ``bytes`` per ``buffers[i]``, exactly ``byteLength`` long.
    """

    def __init__(self, doc: dict[str, Any], bin_chunk: bytes | None, *, max_elements: int, label: str | None) -> None:
        if not isinstance(doc, dict):
            raise InvalidFileError("the glTF JSON is not an object", label)
        self.doc = doc
        self.label = label
        self.max_elements = max_elements
        self.budget = ParseBudget(label)
        self._check_external_images()
        self.buffers = self._resolve_buffers(bin_chunk)

    # ----- typed JSON access -----------------------------------------------------------------------------------
    def fail(self, problem: str) -> InvalidFileError:
        """An InvalidFileError for this file."""
        return InvalidFileError(problem, self.label)

    def array(self, key: str) -> list[Any]:
        """The top-level array ``key`` (empty if absent)."""
        value = self.doc.get(key, [])
        if not isinstance(value, list):
            raise self.fail(f"'{key}' must be an array")
        return value

    def item(self, key: str, index: Any, where: str) -> dict[str, Any]:
        """The object ``doc[key][index]``, checking that ``index`` is a valid integer index."""
        items = self.array(key)
        i = self.index(index, len(items), where)
        obj = items[i]
        if not isinstance(obj, dict):
            raise self.fail(f"{key}[{i}] must be an object")
        return obj

    def index(self, value: Any, size: int, where: str) -> int:
        """``value`` as an index into an array of ``size`` items."""
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < size:
            raise self.fail(f"{where} = {value!r} is not a valid index (0..{size - 1})")
        return value

    def get_int(self, obj: dict[str, Any], key: str, where: str, default: int | None = None, minimum: int = 0) -> int:
        """An integer property (``default`` when absent and allowed)."""
        value = obj.get(key, default)
        if value is None:
            raise self.fail(f"{where}.{key} is required")
        if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
            raise self.fail(f"{where}.{key} = {value!r} must be an integer >= {minimum}")
        return value

    def get_floats(self, obj: dict[str, Any], key: str, size: int, where: str, default: list[float]) -> np.ndarray:
        """A fixed-size array of finite numbers, as float64."""
        value = obj.get(key, default)
        if (
            not isinstance(value, list)
            or len(value) != size
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
        ):
            raise self.fail(f"{where}.{key} must be an array of {size} numbers")
        out = np.asarray(value, dtype=np.float64)
        if not np.isfinite(out).all():
            raise self.fail(f"{where}.{key} contains NaN or infinite values")
        return out

    # ----- buffers and images -------------------------------------------------------------------------------------
    def _check_external_images(self) -> None:
        for i, image in enumerate(self.array("images")):
            if not isinstance(image, dict):
                raise self.fail(f"images[{i}] must be an object")
            uri = image.get("uri")
            if uri is not None:
                if not isinstance(uri, str):
                    raise self.fail(f"images[{i}].uri must be a string")
                if not uri.startswith("data:"):
                    decode_data_uri(uri, f"images[{i}]", self.label)  # raises, naming the URI
            elif "bufferView" not in image:
                raise self.fail(f"images[{i}] has neither a bufferView nor a data: URI")

    def _resolve_buffers(self, bin_chunk: bytes | None) -> list[bytes]:
        out: list[bytes] = []
        for i, buf in enumerate(self.array("buffers")):
            if not isinstance(buf, dict):
                raise self.fail(f"buffers[{i}] must be an object")
            length = self.get_int(buf, "byteLength", f"buffers[{i}]", minimum=1)
            uri = buf.get("uri")
            if uri is None:
                if i != 0 or bin_chunk is None:
                    raise self.fail(f"buffers[{i}] has no uri and there is no GLB binary chunk for it")
                data = bin_chunk
            else:
                if not isinstance(uri, str):
                    raise self.fail(f"buffers[{i}].uri must be a string")
                self.budget.charge(len(uri), f"buffers[{i}] (a data: URI)")
                data, _ = decode_data_uri(uri, f"buffers[{i}]", self.label)
            if len(data) < length:
                raise self.fail(f"buffers[{i}] declares {length} bytes but only {len(data)} are present (truncated?)")
            out.append(data[:length] if len(data) != length else data)
        return out

    def buffer_view(self, index: Any, where: str) -> tuple[bytes, int, int, int | None]:
        """(buffer bytes, byteOffset, byteLength, byteStride) of ``bufferViews[index]``, range-checked."""
        view = self.item("bufferViews", index, where)
        name = f"bufferViews[{index}]"
        b = self.index(view.get("buffer"), len(self.buffers), f"{name}.buffer")
        offset = self.get_int(view, "byteOffset", name, default=0)
        length = self.get_int(view, "byteLength", name, minimum=1)
        stride = view.get("byteStride")
        if stride is not None:
            stride = self.get_int(view, "byteStride", name, minimum=1)
        if offset + length > len(self.buffers[b]):
            raise self.fail(
                f"{name} (offset {offset}, length {length}) runs past the end of buffers[{b}] ({len(self.buffers[b])} bytes)"
            )
        return self.buffers[b], offset, length, stride

    def image(self, index: Any, where: str) -> tuple[bytes, str | None]:
        """Bytes and MIME type of ``images[index]`` (embedded: bufferView or data: URI)."""
        image = self.item("images", index, where)
        mime = image.get("mimeType") if isinstance(image.get("mimeType"), str) else None
        if "bufferView" in image:
            data, offset, length, _ = self.buffer_view(image["bufferView"], f"images[{index}].bufferView")
            return bytes(data[offset : offset + length]), mime
        data, uri_mime = decode_data_uri(image["uri"], f"images[{index}]", self.label)
        return data, mime or uri_mime

    # ----- accessors --------------------------------------------------------------------------------------------
    def _strided(
        self, view_index: Any, extra_offset: int, count: int, dtype: np.dtype, shape: tuple[int, int], where: str
    ) -> np.ndarray:
        """A copy of ``count`` elements ``(count, cols, rows)`` read from a buffer view, bounds-checked."""
        cols, rows = shape
        comp = dtype.itemsize
        column_stride = _align4(rows * comp) if cols > 1 else rows * comp
        element = cols * column_stride
        data, offset, length, stride = self.buffer_view(view_index, f"{where}.bufferView")
        step = stride if stride is not None else element
        if step < element:
            raise self.fail(f"{where}: byteStride {step} is smaller than one element ({element} bytes)")
        end = extra_offset + (count - 1) * step + element
        if end > length:
            raise self.fail(
                f"{where}: {count} elements from byteOffset {extra_offset} need {end} bytes but its bufferView has {length}"
            )
        arr = np.ndarray(
            shape=(count, cols, rows),
            dtype=dtype,
            buffer=data,
            offset=offset + extra_offset,
            strides=(step, column_stride, comp),
        )
        return arr.copy()

    def accessor_count(self, index: Any, where: str) -> int:
        """The declared element count of ``accessors[index]`` (to check limits before decoding)."""
        acc = self.item("accessors", index, where)
        return self.get_int(acc, "count", f"accessors[{index}]", minimum=1)

    def accessor(self, index: Any, where: str, *, allowed_types: tuple[str, ...] | None = None) -> np.ndarray:
        """Decoded values of ``accessors[index]``: ``(count,)`` for SCALAR, ``(count, n)`` for VECn and
        ``(count, n, n)`` (row, column) for MATn. Floats and normalized integers come back as float32 (normalized
        values mapped to [0, 1] or [-1, 1]); other integers keep their dtype. Sparse values are applied."""
        acc = self.item("accessors", index, where)
        name = f"accessors[{index}]"
        ctype = acc.get("componentType")
        if ctype not in COMPONENT_DTYPES:
            raise self.fail(f"{name}.componentType = {ctype!r} is not a glTF component type")
        atype = acc.get("type")
        if atype not in TYPE_SHAPES:
            raise self.fail(f"{name}.type = {atype!r} is not a glTF accessor type")
        if allowed_types is not None and atype not in allowed_types:
            raise self.fail(f"{name} ({where}) has type {atype}, expected {' or '.join(allowed_types)}")
        dtype = COMPONENT_DTYPES[ctype]
        cols, rows = TYPE_SHAPES[atype]
        count = self.get_int(acc, "count", name, minimum=1)
        if count * cols * rows > self.max_elements:
            raise LimitExceededError(
                f"{name} has {count} x {cols * rows} values, over the limit of {self.max_elements} (max_accessor_elements)",
                self.label,
            )
        self.budget.charge(count * cols * rows * DECODED_BYTES_PER_VALUE, f"{name} ({count} x {atype})")
        normalized = acc.get("normalized", False)
        if not isinstance(normalized, bool):
            raise self.fail(f"{name}.normalized must be a boolean")
        if normalized and ctype in (5125, 5126):
            raise self.fail(f"{name} is normalized but its componentType ({ctype}) cannot be")
        offset = self.get_int(acc, "byteOffset", name, default=0)
        if "bufferView" in acc:
            values = self._strided(acc["bufferView"], offset, count, dtype, (cols, rows), name)
        else:
            values = np.zeros((count, cols, rows), dtype=dtype)
        if "sparse" in acc:
            self._apply_sparse(acc["sparse"], values, name)
        # (count, cols, rows) -> (count, rows, cols) so that m[i][r, c] is row r, column c.
        values = values.transpose(0, 2, 1)
        if normalized:
            info = np.iinfo(dtype)
            values = values.astype(np.float32) / np.float32(info.max)
            if info.min < 0:
                values = np.maximum(values, np.float32(-1.0))
        if atype == "SCALAR":
            return np.ascontiguousarray(values[:, 0, 0])
        if cols == 1:
            return np.ascontiguousarray(values[:, :, 0])
        return np.ascontiguousarray(values)

    def _apply_sparse(self, sparse: Any, values: np.ndarray, name: str) -> None:
        where = f"{name}.sparse"
        if not isinstance(sparse, dict):
            raise self.fail(f"{where} must be an object")
        count = values.shape[0]
        n = self.get_int(sparse, "count", where, minimum=1)
        if n > count:
            raise self.fail(f"{where}.count = {n} is more than the accessor's {count} elements")
        indices, vals = sparse.get("indices"), sparse.get("values")
        if not isinstance(indices, dict) or not isinstance(vals, dict):
            raise self.fail(f"{where} needs 'indices' and 'values' objects")
        itype = indices.get("componentType")
        if itype not in SPARSE_INDEX_TYPES:
            raise self.fail(f"{where}.indices.componentType = {itype!r} must be 5121, 5123 or 5125")
        idx = self._strided(
            indices.get("bufferView"), self.get_int(indices, "byteOffset", f"{where}.indices", default=0),
            n, COMPONENT_DTYPES[itype], (1, 1), f"{where}.indices",
        )[:, 0, 0].astype(np.int64)  # fmt: skip
        if idx.size and (idx.max() >= count or (np.diff(idx) <= 0).any()):
            raise self.fail(f"{where}.indices must be strictly increasing and below the accessor count {count}")
        cols, rows = values.shape[1:]
        sub = self._strided(
            vals.get("bufferView"), self.get_int(vals, "byteOffset", f"{where}.values", default=0),
            n, values.dtype, (cols, rows), f"{where}.values",
        )  # fmt: skip
        values[idx] = sub


def require_finite(values: np.ndarray, what: str, label: str | None) -> np.ndarray:
    """``values`` unchanged if every entry is finite; InvalidFileError naming ``what`` otherwise."""
    if values.dtype.kind == "f" and not np.isfinite(values).all():
        bad = int((~np.isfinite(values)).reshape(values.shape[0], -1).any(axis=1).sum()) if values.ndim else 1
        raise InvalidFileError(f"{what} contains NaN or infinite values ({bad} elements)", label)
    return values


def check_extensions(doc: dict[str, Any], supported: set[str], label: str | None) -> None:
    """UnsupportedFileError if the file requires an extension this reader does not implement."""
    required = doc.get("extensionsRequired", [])
    if not isinstance(required, list):
        raise InvalidFileError("'extensionsRequired' must be an array", label)
    missing = [str(e) for e in required if e not in supported]
    if missing:
        raise UnsupportedFileError(
            f"the file requires glTF extensions this reader does not support: {', '.join(missing)}", label
        )


def finite_number(value: Any) -> bool:
    """True for a finite int or float (not bool)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
