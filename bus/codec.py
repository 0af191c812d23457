"""The followbus frame: the one definition of the bytes of a bus message (encode, decode, peek).

Everything that reads or writes message bytes goes through this module: the typed messages
(bus/schemas.py), the recorder, replay and the MCAP reader. :data:`FRAME_FORMAT` is the normative
description of the layout; it is stored as the schema of every bus channel of a recording, so a
reader needs nothing else. In short: ``b"FB1" | u32 little-endian length N | msgpack map (N bytes) |
array blobs``; the map is ``{"_t": type name, "_v": schema version, "header": [...], ...fields}``;
small arrays travel inline as ext type 1, arrays of 4 KiB and more out of band as ext type 2
referencing the blob area, so a 720p frame is copied once on encode (into the joined frame, or, through
:func:`pack_parts`, by bus/pubsub.py straight into a shared-memory buffer) and decoded zero-copy
(``np.frombuffer``): decoded arrays are read-only views of the bytes given to :func:`unpack`.
A recording stores a frame as plain MessagePack, the array ``[head, blob area]`` (:data:`RECORD_FORMAT`,
:func:`frame_to_record`), and gets the frame back byte for byte (:func:`record_to_frame`).
"""

from __future__ import annotations

import json
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import msgpack
import numpy as np

NDARRAY_EXT = 1
NDARRAY_REF_EXT = 2
MAGIC = b"FB1"
LENGTH_BYTES = 4
HEAD_OFFSET = len(MAGIC) + LENGTH_BYTES
_PREFIX = struct.Struct(f"<{len(MAGIC)}sI")  # magic, head length N
INLINE_MAX_BYTES = 4096
_ALLOWED_DTYPES = frozenset(
    {"|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "<f2", "<f4", "<f8", "|b1"}
)
TYPE_KEY, VERSION_KEY, HEADER_KEY = "_t", "_v", "header"


class DecodeError(ValueError):
    """A payload that is not a valid followbus message. Subscribers count and drop these."""


# --- the header every message carries --------------------------------------------------------------

@dataclass
class Header:
    """``stamp_ns`` is the capture stamp of the camera frame the message derives from (so latency = now -
    stamp_ns, and replays are deterministic), ``frame_seq`` that frame's sequence number, ``pub_ns`` the
    wall-clock time of publication. ``epoch_ns`` names the numbering ``frame_seq`` belongs to (the start
    time of the capture session that numbered the frame). ``feedback``: for each feedback input of a
    frame-synchronised output, the frame_seq of the message the node used (-1: none)."""

    seq: int = 0
    stamp_ns: int = 0
    frame_seq: int = -1
    source: str = ""
    pub_ns: int = 0
    epoch_ns: int = 0  # 0: unknown (messages not derived from a camera frame, old recordings)
    feedback: dict[str, int] = field(default_factory=dict)

    def to_wire(self) -> list[Any]:
        return [self.seq, self.stamp_ns, self.frame_seq, self.source, self.pub_ns, self.epoch_ns, self.feedback]


# (name, wire type, meaning): the order of the header array. The first LEGACY_HEADER_FIELDS are all that
# recordings made before epoch and provenance existed carry.
HEADER_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("seq", "int", "per-publisher message counter"),
    ("stamp_ns", "int", "capture stamp of the camera frame the message derives from, ns since the Unix epoch"),
    ("frame_seq", "int", "sequence number of that frame, -1 when not derived from a frame"),
    ("source", "str", "name of the publishing node"),
    ("pub_ns", "int", "publication wall clock, ns since the Unix epoch"),
    ("epoch_ns", "int", "start time of the capture session that numbered frame_seq, 0 when unknown"),
    ("feedback", "map str -> int", "feedback input name -> frame_seq of the message joined (-1: none)"),
)
LEGACY_HEADER_FIELDS = 5


def _header_error(value: Any) -> DecodeError:
    for (name, kind, _meaning), element in zip(HEADER_FIELDS, value, strict=False):  # a 5-element header too
        wanted = int if kind == "int" else str if kind == "str" else dict
        if type(element) is not wanted:
            return DecodeError(f"header.{name}: expected {kind}, got {type(element).__name__}")
    return DecodeError("header.feedback must map input names to frame numbers")


def header_from_wire(value: Any) -> tuple[Header, bool]:
    """(Header, whether it carries epoch and provenance) of a decoded header array; DecodeError if malformed."""
    n = len(value) if isinstance(value, (list, tuple)) else 0
    if n not in (LEGACY_HEADER_FIELDS, len(HEADER_FIELDS)):
        raise DecodeError(f"header: expected a {LEGACY_HEADER_FIELDS}- or {len(HEADER_FIELDS)}-element header")
    # Spelled out rather than looped over HEADER_FIELDS: every message of a replay is peeked several times.
    # `type(x) is int`, not isinstance: a bool is not a number here.
    v = value
    if not (type(v[0]) is int and type(v[1]) is int and type(v[2]) is int and type(v[3]) is str
            and type(v[4]) is int):
        raise _header_error(v)
    if n == LEGACY_HEADER_FIELDS:
        return Header(v[0], v[1], v[2], v[3], v[4]), False
    feedback = v[6]
    if not (type(v[5]) is int and type(feedback) is dict
            and (not feedback or all(type(k) is str and type(f) is int for k, f in feedback.items()))):
        raise _header_error(v)
    return Header(v[0], v[1], v[2], v[3], v[4], v[5], feedback), True


# --- the normative description ---------------------------------------------------------------------

def _header_lines() -> str:
    return "\n".join(f"    {i}. {name} ({kind}): {meaning}" for i, (name, kind, meaning) in enumerate(HEADER_FIELDS))


FRAME_FORMAT = f"""\
FRAME FORMAT (followbus frame, version 1)

One message is one frame of bytes. Fixed-width integers are unsigned and little-endian.

  offset  bytes  content
  0       {len(MAGIC)}      magic: the ASCII bytes "{MAGIC.decode()}"
  {len(MAGIC)}       {LENGTH_BYTES}      N: uint32 little-endian, the byte length of the head
  {HEAD_OFFSET}       N      head: exactly one MessagePack value (https://msgpack.org), a map
  {HEAD_OFFSET}+N     rest   blob area: array bytes referenced from the head (empty when none are)

Head map. Keys are MessagePack str; text values are str (UTF-8), byte strings bin:
  "{TYPE_KEY}"      str: the message type name (the schema name without its "followbus." prefix)
  "{VERSION_KEY}"      int: the version of the message type's field list (VERSION under FIELDS)
  "{HEADER_KEY}"  array of {len(HEADER_FIELDS)} elements, in this order (recordings made before epoch_ns existed
            carry only the first {LEGACY_HEADER_FIELDS}; read epoch_ns as 0 and feedback as an empty map):
{_header_lines()}
  then one key per field of the message type (listed under FIELDS); nil where a field is optional
  and absent. Writers put "{TYPE_KEY}", "{VERSION_KEY}" and "{HEADER_KEY}" first (a reader may stop after them).

Arrays (numpy n-dimensional arrays, elements in C order) are MessagePack ext values, in one of
two forms, either of which may appear wherever a field holds an array:
  ext type {NDARRAY_EXT} (inline): ext data = dtype, a 0x00 byte, shape, a 0x00 byte, then the element bytes;
      dtype is ASCII, shape is a JSON array of non-negative ints in ASCII (e.g. [480, 640, 3]).
  ext type {NDARRAY_REF_EXT} (out of band): ext data = a MessagePack array [dtype (str), shape (array of int),
      offset (int), nbytes (int)]; the elements are the blob area's bytes offset .. offset+nbytes-1
      (offsets count from the start of the blob area, not of the frame).
  In both forms the element bytes number product(shape) * itemsize; shape [] is one element.
  dtype is a numpy array-interface type string: byte order ("<" little-endian, "|" single byte),
  kind (u unsigned int, i signed int, f IEEE 754 float, b bool stored as one byte 0 or 1) and
  itemsize in bytes. Allowed: {" ".join(sorted(_ALLOWED_DTYPES))}.
  Writers put arrays of fewer than {INLINE_MAX_BYTES} bytes inline, larger ones out of band, blobs in the
  order the head references them; numpy scalars are written as plain MessagePack numbers.
"""


# --- pack / unpack: the frame around any map -------------------------------------------------------

def _array_meta(arr: np.ndarray) -> np.ndarray:
    arr = np.ascontiguousarray(arr)
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    if arr.dtype.str not in _ALLOWED_DTYPES:
        raise TypeError(f"array dtype {arr.dtype} cannot be sent")
    return arr


_DTYPES = {name: np.dtype(name) for name in _ALLOWED_DTYPES}


def _check_meta(dtype_str: Any, shape: Any) -> tuple[np.dtype, tuple[int, ...], int]:
    dtype = _DTYPES.get(dtype_str) if isinstance(dtype_str, str) else None
    if dtype is None:
        raise DecodeError(f"array dtype {dtype_str!r} not allowed")
    if not isinstance(shape, (list, tuple)) or not all(isinstance(n, int) and n >= 0 for n in shape):
        raise DecodeError(f"bad array shape {shape!r}")
    count = 1
    for n in shape:  # Python ints: no overflow, where np.prod would wrap a hostile shape
        count *= n
    return dtype, tuple(shape), count * dtype.itemsize


def pack_parts(obj: Mapping[str, Any]) -> tuple[bytes, list[np.ndarray]]:
    """A frame in two parts: magic, length and head as bytes, then the arrays of its blob area in order.

    Nothing of the arrays is copied: a writer puts the parts one after the other wherever the frame goes
    (:func:`pack` joins them; bus/pubsub.py writes them straight into a shared-memory buffer).
    """
    blobs: list[np.ndarray] = []
    offset = 0

    def default(value: Any) -> Any:
        nonlocal offset
        if isinstance(value, np.ndarray):
            arr = _array_meta(value)
            if arr.nbytes < INLINE_MAX_BYTES:
                # the shape as json.dumps writes it ("[2, 4]"), without json's per-call overhead
                head = f"{arr.dtype.str}\0[{', '.join(map(str, arr.shape))}]\0".encode()
                return msgpack.ExtType(NDARRAY_EXT, head + arr.tobytes())
            ref = msgpack.packb([arr.dtype.str, list(arr.shape), offset, arr.nbytes])
            blobs.append(arr)
            offset += arr.nbytes
            return msgpack.ExtType(NDARRAY_REF_EXT, ref)
        if isinstance(value, np.generic):
            return value.item()
        raise TypeError(f"cannot encode {type(value).__name__}")

    head = msgpack.packb(obj, default=default, use_bin_type=True)
    return _PREFIX.pack(MAGIC, len(head)) + head, blobs


def pack(obj: Mapping[str, Any]) -> bytes:
    """Frame a plain map (values: scalars, str, bytes, lists, dicts, numpy arrays)."""
    head, blobs = pack_parts(obj)
    if not blobs:
        return head
    # One join: each large array is copied exactly once, into the frame.
    return b"".join([head, *(memoryview(b).cast("B") for b in blobs)])


INT_MIN, INT_LIMIT = -(2**63), 2**64  # the integers MessagePack carries


def wire_value(value: Any, *, share_arrays: bool = False) -> Any:
    """What :func:`unpack` gives back for ``value`` written by :func:`pack_parts`, made without the bytes:
    the in-process runtime's copy of a message field (bus/inproc.py). An array becomes a read-only private
    copy, C-ordered and little-endian, as the reader's view of the frame would be; lists, tuples and maps are
    copied element by element. Any other type than plain None, bool, int, float, ASCII str, list, tuple and
    str-keyed dict (a numpy scalar, a subclass, bytes, a large int...) takes the real way, written and read
    back, so the rules are the writer's and the reader's by construction: what cannot be written raises as
    :func:`pack_parts` does (TypeError, ...), what would not read back raises :class:`DecodeError`.
    ``share_arrays``: a C-ordered little-endian array (``value`` itself) is not copied but viewed read-only,
    for a caller that hands it over and never writes to it again."""
    kind = type(value)
    if kind is float or kind is bool or value is None:
        return value
    if kind is int:
        return value if INT_MIN <= value < INT_LIMIT else _round_trip(value)
    if kind is str:
        return value if value.isascii() else _round_trip(value)
    if kind is np.ndarray:
        arr = _array_meta(value)
        arr = arr.view() if share_arrays and arr is value else np.array(arr, copy=True)
        arr.flags.writeable = False
        return arr
    if kind is list or kind is tuple:
        return [wire_value(item) for item in value]
    if kind is dict and all(type(key) is str and key.isascii() for key in value):
        return {key: wire_value(item) for key, item in value.items()}
    return _round_trip(value)


def _round_trip(value: Any) -> Any:
    return unpack(pack({"v": value}))["v"]


def _split(data: bytes | bytearray | memoryview,
           blob_area: memoryview | None = None) -> tuple[memoryview, memoryview]:
    """(head, blob area) views of a frame; ``blob_area`` given: the frame is its head only and its arrays
    are there (a message of bus/shmlane.py's lane)."""
    if len(data) < HEAD_OFFSET:
        raise DecodeError("not a followbus message (too short)")
    magic, head_len = _PREFIX.unpack_from(data)
    if magic != MAGIC:
        raise DecodeError("not a followbus message (bad magic)")
    if HEAD_OFFSET + head_len > len(data):
        raise DecodeError(f"truncated message: header of {head_len} bytes, {len(data) - HEAD_OFFSET} present")
    view = memoryview(data)
    if blob_area is not None:
        if HEAD_OFFSET + head_len != len(data):
            raise DecodeError("lane message: bytes after the head")
        return view[HEAD_OFFSET:], blob_area
    return view[HEAD_OFFSET:HEAD_OFFSET + head_len], view[HEAD_OFFSET + head_len:]


def _shape(raw: bytes) -> Any:
    """An inline array's shape: the form writers use ("[480, 640, 3]") read directly, anything else by json
    (a message carries several small arrays, and json.loads would be the largest part of decoding each)."""
    if raw[:1] == b"[" and raw[-1:] == b"]":
        inner = raw[1:-1]
        parts = inner.split(b", ") if inner else []
        # digits without a leading zero: exactly the JSON integers >= 0 (json.loads rejects "007")
        if all(p.isdigit() and (p[:1] != b"0" or len(p) == 1) for p in parts):
            return [int(p) for p in parts]
    return json.loads(raw)


def unpack(data: bytes | bytearray | memoryview, blob_area: memoryview | None = None) -> dict[str, Any]:
    """Decode a frame's map; raises :class:`DecodeError` on anything malformed. ``blob_area``: the arrays'
    bytes are there, not after the head (bus/shmlane.py)."""
    head, blob_area = _split(data, blob_area)

    def ext_hook(code: int, ext: bytes) -> Any:
        if code == NDARRAY_EXT:
            try:
                first = ext.index(b"\0")
                second = ext.index(b"\0", first + 1)
                dtype, shape, nbytes = _check_meta(ext[:first].decode(), _shape(ext[first + 1 : second]))
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
        obj = msgpack.unpackb(head, ext_hook=ext_hook, raw=False, strict_map_key=True)
    except DecodeError:
        raise
    except Exception as exc:  # msgpack raises a zoo of exception types on garbage
        raise DecodeError(f"not msgpack: {exc}") from exc
    if not isinstance(obj, dict):
        raise DecodeError(f"expected a map at top level, got {type(obj).__name__}")
    return obj


# --- messages: type, version, header and fields ----------------------------------------------------

class Decoded(NamedTuple):
    type_name: Any  # as found: the caller checks it against its message types
    version: Any
    header: Header | None  # None: the map has no header
    fields: dict[str, Any]  # everything else


class Peeked(NamedTuple):
    type_name: str
    version: Any
    header: Header
    provenance: bool  # the header carries epoch_ns and feedback (False: an old recording's 5-element header)


def encode_message(type_name: str, version: int, header: Header, fields: Mapping[str, Any]) -> bytes:
    """A message's frame: type, version and header first (what :func:`peek` reads), then the fields."""
    return pack({TYPE_KEY: type_name, VERSION_KEY: version, HEADER_KEY: header.to_wire(), **fields})


def encode_message_parts(type_name: str, version: int, header: Header,
                         fields: Mapping[str, Any]) -> tuple[bytes, list[np.ndarray]]:
    """:func:`encode_message` as :func:`pack_parts` gives it: the frame's head and its blob arrays, uncopied."""
    return pack_parts({TYPE_KEY: type_name, VERSION_KEY: version, HEADER_KEY: header.to_wire(), **fields})


def decode_message(data: bytes | bytearray | memoryview, blob_area: memoryview | None = None) -> Decoded:
    """Split a frame into type name, version, header and the remaining fields (arrays decoded)."""
    obj = unpack(data, blob_area)
    raw_header = obj.pop(HEADER_KEY, None)
    header = None if raw_header is None else header_from_wire(raw_header)[0]
    return Decoded(obj.pop(TYPE_KEY, None), obj.pop(VERSION_KEY, None), header, obj)


def peek(data: bytes | bytearray | memoryview) -> Peeked:
    """Type, version and header of a frame without decoding its fields or arrays; DecodeError if it has none."""
    head, _ = _split(data)
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=True)
    unpacker.feed(head)
    found: dict[str, Any] = {}
    try:
        for _ in range(unpacker.read_map_header()):
            key = unpacker.unpack()
            if key in (TYPE_KEY, VERSION_KEY, HEADER_KEY):
                found[key] = unpacker.unpack()
                if len(found) == 3:
                    break
            else:
                unpacker.skip()  # skipped, not decoded: the arrays of a field cost nothing here
    except (ValueError, TypeError, msgpack.UnpackException, msgpack.OutOfData) as exc:
        raise DecodeError(f"not msgpack: {exc}") from exc
    type_name = found.get(TYPE_KEY)
    if not isinstance(type_name, str):
        raise DecodeError(f"no message type ({TYPE_KEY!r}: {type_name!r})")
    if HEADER_KEY not in found:
        raise DecodeError(f"{type_name}: no header")
    header, provenance = header_from_wire(found[HEADER_KEY])
    return Peeked(type_name, found.get(VERSION_KEY), header, provenance)


def frame_parts(data: bytes | bytearray | memoryview) -> tuple[memoryview, memoryview]:
    """(head, blob area) views of an encoded message, neither decoded (a malformed one: DecodeError): what a
    comparison of two messages' bytes needs (replay/diff.py)."""
    return _split(data)


# --- a frame as a recording stores it: one MessagePack document --------------------------------------

RECORD_ARRAY = b"\x92"  # MessagePack fixarray of 2 elements: [head, blob area]
BIN32 = 0xC6
_BLOB_BIN = struct.Struct(">BI")  # bin32 marker and length (MessagePack is big-endian)
_HEAD_FEED_BYTES = 64 * 1024  # the head is small; the blob area behind it is never fed to the unpacker

RECORD_FORMAT = f"""\
RECORD FORMAT (a followbus frame in a recording, message_encoding "msgpack")

Each message of a bus channel is exactly one MessagePack value, an array of 2 elements [head, blob area]:
  0x{RECORD_ARRAY.hex()}   the array marker (fixarray of 2 elements)
  head   the frame's head (below), its very bytes: a map, which any MessagePack library reads
  0x{BIN32:02x}   bin 32 marker, then the blob area's byte length as uint32 big-endian (this form always,
         even when the blob area is empty), then the blob area's bytes (below)
The head's arrays are MessagePack ext values (types {NDARRAY_EXT} and {NDARRAY_REF_EXT} below); the offset of an
ext type {NDARRAY_REF_EXT} array counts from the start of the blob area, the bin's bytes.
The followbus frame is the bytes "{MAGIC.decode()}", the head's byte length as uint32 little-endian, the head
and the blob area: followbus replays it byte for byte. Recordings made before stored that frame itself
(message_encoding "x-followbus-frame/1", or "msgpack" on bytes starting with "{MAGIC.decode()}"): they still read.
"""


def _value_length(view: memoryview) -> int:
    """The byte length of the one MessagePack value ``view`` starts with, fed to the unpacker a piece at a time
    (what follows a frame's head is its blobs, megabytes of them); DecodeError when it is not one."""
    unpacker = msgpack.Unpacker()
    fed, piece = 0, _HEAD_FEED_BYTES
    while True:
        unpacker.feed(view[fed:fed + piece])
        fed += piece
        try:
            unpacker.skip()
            return unpacker.tell()
        except msgpack.OutOfData:
            if fed >= len(view):
                raise DecodeError("truncated: the head is not a complete MessagePack value") from None
            piece *= 2
        except Exception as exc:  # msgpack raises a zoo of exception types on garbage
            raise DecodeError(f"not msgpack: {exc!r}") from exc


def frame_to_record(frame: bytes | bytearray | memoryview) -> bytes:
    """The MessagePack array ``[head, blob area]`` a recording stores for a frame (:data:`RECORD_FORMAT`): the
    head's bytes as they are (never decoded and written again), the blobs copied once. DecodeError when
    ``frame`` is not a frame whose head is one MessagePack value (such bytes cannot be stored this way)."""
    head, blobs = _split(frame)
    if _value_length(head) != len(head):
        raise DecodeError("the head holds more than one MessagePack value")
    return b"".join((RECORD_ARRAY, head, _BLOB_BIN.pack(BIN32, len(blobs)), blobs))


def record_to_frame(data: bytes | bytearray | memoryview) -> bytes:
    """The frame a bus channel's message holds, byte for byte as it was published: a ``[head, blob area]``
    array (:func:`frame_to_record`) made a frame again; a frame (recordings made before) as it is.
    DecodeError for anything else (a truncated or foreign message)."""
    if data[:len(MAGIC)] == MAGIC:
        return bytes(data)
    view = memoryview(data)
    if view[:1] != RECORD_ARRAY:
        raise DecodeError("neither a followbus frame nor a recorded [head, blob area] array")
    head_end = 1 + _value_length(view[1:])
    if len(view) < head_end + _BLOB_BIN.size:
        raise DecodeError("truncated: no blob area after the head")
    marker, size = _BLOB_BIN.unpack_from(view, head_end)
    blobs_at = head_end + _BLOB_BIN.size
    if marker != BIN32 or blobs_at + size != len(view):
        raise DecodeError(f"the blob area is not a bin 32 of the {len(view) - blobs_at} bytes after the head")
    return b"".join((_PREFIX.pack(MAGIC, head_end - 1), view[1:head_end], view[blobs_at:]))
