"""msgpack codec with numpy arrays.

Wire format: ``b"FB1" | u32 little-endian length N | msgpack map (N bytes) | array blobs``.
The map is ``{"_t": type name, "_v": schema version, ...fields}``. Small arrays travel inline as
ext type 1 (``dtype \\0 shape-json \\0 bytes``); arrays of 4 KiB and more travel out of band as
ext type 2 (``[dtype, shape, offset, nbytes]`` into the blob area), so a 720p frame is copied
once on encode and decoded zero-copy (``np.frombuffer``): decoded arrays are read-only views.
"""

from __future__ import annotations

import json
from typing import Any

import msgpack
import numpy as np

NDARRAY_EXT = 1
NDARRAY_REF_EXT = 2
MAGIC = b"FB1"
INLINE_MAX_BYTES = 4096
_ALLOWED_DTYPES = frozenset(
    {"|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8", "|b1"}
)


class DecodeError(ValueError):
    """A payload that is not a valid followbus message. Subscribers count and drop these."""


def _array_meta(arr: np.ndarray) -> np.ndarray:
    arr = np.ascontiguousarray(arr)
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    if arr.dtype.str not in _ALLOWED_DTYPES:
        raise TypeError(f"array dtype {arr.dtype} cannot be sent")
    return arr


def _check_meta(dtype_str: Any, shape: Any) -> tuple[np.dtype, tuple[int, ...], int]:
    if dtype_str not in _ALLOWED_DTYPES:
        raise DecodeError(f"array dtype {dtype_str!r} not allowed")
    if not isinstance(shape, (list, tuple)) or not all(isinstance(n, int) and n >= 0 for n in shape):
        raise DecodeError(f"bad array shape {shape!r}")
    dtype = np.dtype(dtype_str)
    return dtype, tuple(shape), int(np.prod(shape, dtype=np.int64)) * dtype.itemsize


def pack(obj: dict[str, Any]) -> bytes:
    """Encode a plain dict (values: scalars, str, bytes, lists, dicts, numpy arrays)."""
    blobs: list[np.ndarray] = []
    offset = 0

    def default(value: Any) -> Any:
        nonlocal offset
        if isinstance(value, np.ndarray):
            arr = _array_meta(value)
            if arr.nbytes < INLINE_MAX_BYTES:
                head = f"{arr.dtype.str}\0{json.dumps(list(arr.shape))}\0".encode()
                return msgpack.ExtType(NDARRAY_EXT, head + arr.tobytes())
            ref = msgpack.packb([arr.dtype.str, list(arr.shape), offset, arr.nbytes])
            blobs.append(arr)
            offset += arr.nbytes
            return msgpack.ExtType(NDARRAY_REF_EXT, ref)
        if isinstance(value, np.generic):
            return value.item()
        raise TypeError(f"cannot encode {type(value).__name__}")

    head = msgpack.packb(obj, default=default, use_bin_type=True)
    return b"".join([MAGIC, len(head).to_bytes(4, "little"), head, *(memoryview(b).cast("B") for b in blobs)])


def unpack(data: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Decode bytes produced by :func:`pack`; raises :class:`DecodeError` on anything malformed."""
    view = memoryview(data)
    if len(view) < 7 or bytes(view[:3]) != MAGIC:
        raise DecodeError("not a followbus message (bad magic)")
    head_len = int.from_bytes(view[3:7], "little")
    if 7 + head_len > len(view):
        raise DecodeError(f"truncated message: header of {head_len} bytes, {len(view) - 7} present")
    blob_area = view[7 + head_len :]

    def ext_hook(code: int, ext: bytes) -> Any:
        if code == NDARRAY_EXT:
            try:
                first = ext.index(b"\0")
                second = ext.index(b"\0", first + 1)
                dtype, shape, nbytes = _check_meta(ext[:first].decode(), json.loads(ext[first + 1 : second]))
            except (ValueError, UnicodeDecodeError) as exc:
                raise DecodeError(f"malformed array header: {exc}") from exc
            body = memoryview(ext)[second + 1 :]
            if len(body) != nbytes:
                raise DecodeError(f"array body is {len(body)} bytes, {shape} {dtype} needs {nbytes}")
            return np.frombuffer(body, dtype=dtype).reshape(shape)
        if code == NDARRAY_REF_EXT:
            try:
                dtype_str, shape, offset, nbytes = msgpack.unpackb(ext)
            except Exception as exc:
                raise DecodeError(f"malformed array reference: {exc}") from exc
            dtype, shape, expected = _check_meta(dtype_str, shape)
            if not (isinstance(offset, int) and offset >= 0 and nbytes == expected
                    and offset + nbytes <= len(blob_area)):
                raise DecodeError(f"array reference out of bounds ({offset}+{nbytes} > {len(blob_area)})")
            return np.frombuffer(blob_area[offset : offset + nbytes], dtype=dtype).reshape(shape)
        raise DecodeError(f"unknown msgpack extension type {code}")

    try:
        obj = msgpack.unpackb(view[7 : 7 + head_len], ext_hook=ext_hook, raw=False, strict_map_key=True)
    except DecodeError:
        raise
    except Exception as exc:  # msgpack raises a zoo of exception types on garbage
        raise DecodeError(f"not msgpack: {exc}") from exc
    if not isinstance(obj, dict):
        raise DecodeError(f"expected a map at top level, got {type(obj).__name__}")
    return obj
