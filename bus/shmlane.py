"""The same-host lane: large arrays in followbus's own sealed shared memory, a small descriptor over Zenoh.

Opt-in (``zenoh: shm_lane: true``; BENCHMARKS.md: it saves nothing measurable end to end at 640x480 and pays
with large frames and several frame subscribers). zenoh-python 1.10 gives a received ``ZBytes``/``ZShm`` no
buffer protocol, so a receiver must copy every payload out of Zenoh's shared memory; the lane carries the
array bytes outside Zenoh instead, where a receiver on the same machine maps them without a copy:

* Writer (:class:`LaneWriter`, one per :class:`~.pubsub.Publisher`): segments are anonymous memory files
  (``memfd_create``, named ``followbus-lane``), nothing in /dev/shm: no name another process can squat or
  leave stale, and they die with the process. Each is sized once, mapped writable by the publisher, then
  sealed with :data:`SEALS` (no shrink, no grow, no new writable mapping or write() by anyone, no more
  seals): no other process can truncate it (SIGBUS in its readers) or rewrite a frame after the store, while
  the writer's own mapping stays writable. A segment is rewritten only under ``flock(LOCK_EX | LOCK_NB)`` and
  no sooner than :data:`REUSE_AFTER_S` after its last write; the writer takes the most recently written free
  one (its pages are still cached), else creates one (up to :data:`MAX_SEGMENTS`; one too small for a
  message is replaced), and with all held by readers answers None (the message goes inline). Every write
  bumps the segment's generation.
* Wire form (:data:`LANE_MAGIC`): ``b"FBL" | u32 N | msgpack [pid, fd, inode, generation, length, host id]
  (N bytes) | the message's frame head`` (bus/codec.py); the head's out-of-band array references point into
  the segment's data instead of a blob area after the head.
* Reader (:func:`open_blob_area`): the descriptor is untrusted (no more than the Zenoh message carrying it, which
  anyone who can reach the bus may publish, and whose sender Zenoh does not authenticate to a subscriber), and
  opening a file is not harmless (a FIFO, a serial port whose open resets the MCU). So nothing is opened until
  the descriptor has passed every check that needs no open: its host id is ours (a descriptor from another
  machine names pids of that machine); ``/proc/<pid>`` is a process of this user (who published it, as the
  kernel sees it); ``/proc/<pid>/fd/<fd>`` reads ``/memfd:followbus-lane (deleted)``. The fd is then pinned
  with ``O_PATH`` (which runs no driver's open) and that very file checked (a regular file of this user, the
  inode named, still our memfd's name), and only then reopened read-only through ``/proc/self/fd`` (the kernel
  allows ``/proc/<pid>/fd`` to processes that may ptrace-read the publisher: same user, dumpable; a publisher
  that made itself non-dumpable with ``PR_SET_DUMPABLE`` 0 could not be read, so followbus never does that).
  The open file must carry exactly :data:`SEALS` and be large enough; then ``flock(LOCK_SH | LOCK_NB)``, a
  read-only mapping (kept between messages), magic, generation and length. Decoded arrays are read-only
  numpy views of that mapping; the shared lock is held until the last array of the message is gone, so a
  received array stays valid and unchanged after the handler returns, as for an inline message. A segment
  rewritten since the descriptor was sent, or whose process is gone, raises :class:`LaneStale` (a drop);
  anything else wrong, DecodeError (a decode error).
* Who gets descriptors: lane subscribers (bus/pubsub.py) take messages on a side key, ``<key>/@lane`` (an
  ``@`` chunk: no ``**`` subscription matches it), and declare a liveliness token
  ``@followbus/lane/<host id>/<unique id>/<key expression, hex>`` (:func:`declare_token`) before their
  subscriber. A publisher follows those tokens (``LaneWriter.ready``) and sends descriptors on the side key
  only while at least one token matches its key, every matching token carries its own host id (boot id,
  pid namespace, user) and there are no more than :data:`MAX_TRACKED_TOKENS` of them (a flood of tokens makes
  it send inline, and costs it no memory beyond the bound); anything else (a subscriber on another machine,
  in a container with its own pids, of another user) gets inline messages on the side key. The real key
  always carries the real message whenever anyone subscribes to it (a plain Zenoh program, a bridge, the
  recorder): the publisher asks Zenoh's matching status.

bus/ knows no application message: this module moves bytes.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import logging
import mmap
import os
import secrets
import stat
import struct
import threading
import time
import weakref
from collections.abc import Iterable
from typing import Any, NamedTuple

import msgpack
import numpy as np

from .codec import DecodeError

log = logging.getLogger(__name__)

LANE_MAGIC = b"FBL"
_PREFIX = struct.Struct("<3sI")  # lane magic, descriptor length
SEGMENT_MAGIC = b"FBLANE01"
_SEG_HEADER = struct.Struct("<8sQQ")  # magic, generation, length of the data written
DATA_OFFSET = 64  # data starts on a cache line
LANE_THRESHOLD_BYTES = 64 * 1024  # arrays (blob area) from this size take the lane (= zenoh shm's threshold)
# Per publisher. A segment is rewritten no sooner than REUSE_AFTER_S after its last write (so a receiver
# that gets its descriptor that late still reads it), and then the most recently written one is taken: its
# pages are still in the CPU's cache (a 2.76 MB copy: 0.18 ms into a cached segment, 0.31 ms into one of 4
# turned over in rotation, on the 2-core VM). Segments held by readers are skipped; with MAX_SEGMENTS all
# held, the message goes inline; all present but some only younger than REUSE_AFTER_S, the oldest is taken.
REUSE_AFTER_S = 0.015
MAX_SEGMENTS = 8
MAX_LANE_BYTES = 48 * 1024 * 1024  # = pubsub.MAX_PAYLOAD_BYTES: a descriptor naming more is refused
MAX_DESCRIPTOR_BYTES = 256
TOKEN_PREFIX = "@followbus/lane"
MAX_TRACKED_TOKENS = 64  # lane tokens matching one publisher's key it watches; past it: inline
MEMFD_NAME = "followbus-lane"
_MEMFD_LINK = f"/memfd:{MEMFD_NAME} (deleted)"  # what /proc/<pid>/fd/<n> reads for one of our segments
F_SEAL_FUTURE_WRITE = getattr(fcntl, "F_SEAL_FUTURE_WRITE", 0x0010)  # Linux 5.1; Python's fcntl may lack it
# Exactly these, no fewer (a segment someone can shrink, grow or write is refused) and no more (F_SEAL_WRITE
# cannot be added while the writer maps it, so a segment carrying it is not one of ours).
SEALS = fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | F_SEAL_FUTURE_WRITE | fcntl.F_SEAL_SEAL


class LaneStale(DecodeError):
    """The segment was rewritten (or removed) since the descriptor was sent: the message is gone."""


# --- where we are ------------------------------------------------------------------------------------

def _compute_host_id() -> str | None:
    """Whose /proc/<pid>/fd we can open and whose pids we see: the boot id, the pid namespace and the user,
    hashed (a container with its own pids, another user: another "host", served inline). None when this
    kernel has no sealable memfd (the lane is then off)."""
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            boot = f.read().strip()
        pid_ns = os.readlink("/proc/self/ns/pid")
        os.close(os.memfd_create(MEMFD_NAME, os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING))
    except (OSError, AttributeError):
        return None
    return hashlib.sha256(f"{boot}:{pid_ns}:{os.getuid()}".encode()).hexdigest()[:16]


HOST_ID = _compute_host_id()


def side_key(key: str) -> str:
    """Where lane subscribers of ``key`` take its messages (descriptors or inline): an ``@`` chunk, which no
    ``**`` matches, so a plain subscriber of the real key or of ``ns/**`` never sees a descriptor."""
    return f"{key}/@lane"


def token_key(key_expr: str) -> str:
    """A fresh liveliness token key announcing a lane subscription of ``key_expr`` on this host."""
    return f"{TOKEN_PREFIX}/{HOST_ID or 'nolane'}/{secrets.token_hex(8)}/{key_expr.encode().hex()}"


def declare_token(session: Any, key_expr: str) -> Any:
    """Declare this lane subscription's token (before its subscriber); None if Zenoh refused it."""
    try:
        return session.liveliness().declare_token(token_key(key_expr))
    except Exception as exc:  # a closed session: the subscriber fails on its own right after
        log.debug("lane token for %s not declared: %r", key_expr, exc)
        return None


def _parse_token(key: str) -> tuple[str, str] | None:
    """(host id, subscribed key expression) of a token key; None if it is not one."""
    parts = key.split("/")
    if len(parts) != 5 or "/".join(parts[:2]) != TOKEN_PREFIX:
        return None
    try:
        return parts[2], bytes.fromhex(parts[4]).decode()
    except ValueError:
        return None


# --- the writer --------------------------------------------------------------------------------------

class _Segment:
    """A sealed memfd of a fixed capacity, mapped writable by its publisher (see the module doc)."""

    def __init__(self, capacity: int) -> None:
        capacity = -(-capacity // 65536) * 65536
        self.fd = os.memfd_create(MEMFD_NAME, os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
        try:
            os.ftruncate(self.fd, DATA_OFFSET + capacity)
            self.mm = mmap.mmap(self.fd, DATA_OFFSET + capacity, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
            fcntl.fcntl(self.fd, fcntl.F_ADD_SEALS, SEALS)
        except BaseException:
            os.close(self.fd)
            raise
        self.ino = os.fstat(self.fd).st_ino
        self.capacity = capacity
        self.view: np.ndarray | None = np.frombuffer(self.mm, np.uint8)
        self.generation = secrets.randbits(48)
        self.written = 0.0  # time.monotonic() of the last write

    def close(self) -> None:
        self.view = None
        with contextlib.suppress(BufferError):
            self.mm.close()
        os.close(self.fd)


class LaneWriter:
    """One publisher's ring of segments and its view of who subscribes to its key (see the module doc)."""

    def __init__(self, session: Any, key: str):
        if HOST_ID is None:
            raise OSError("no sealable memfd on this kernel")
        import zenoh

        self.key = key
        self._key_expr = zenoh.KeyExpr(key)
        self._segments: list[_Segment] = []  # most recently written first
        self._lock = threading.Lock()
        self._tokens: dict[str, bool] = {}  # token key -> whether it is a subscriber of our key on this host
        self.ready = False  # every known subscriber of the key is a lane one on this host
        self.overflowed = False  # more than MAX_TRACKED_TOKENS tokens matched our key: inline for good
        self.fallbacks = 0  # messages sent inline because every segment was held by readers
        self._live = session.liveliness().declare_subscriber(
            f"{TOKEN_PREFIX}/**", zenoh.handlers.Callback(self._on_token, indirect=False), history=True)

    def _on_token(self, sample: Any) -> None:
        import zenoh

        key = str(sample.key_expr)
        parsed = _parse_token(key)
        if parsed is None:
            return
        host, expr = parsed
        try:
            relevant = self._key_expr.intersects(expr)
        except Exception:
            relevant = True  # a key expression we cannot read: assume it wants ours, inline
            host = ""
        if not relevant:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._tokens.pop(key, None)
            elif len(self._tokens) < MAX_TRACKED_TOKENS:
                self._tokens[key] = host == HOST_ID
            else:  # a flood of tokens (or a very wide fan-out): stop counting them, stay inline
                self.overflowed = True
            self.ready = bool(self._tokens) and all(self._tokens.values()) and not self.overflowed

    def write(self, blobs: list[np.ndarray], nbytes: int) -> bytes | None:
        """Write the arrays one after the other into a free segment; the descriptor (msgpack), or None when
        every segment is held by readers and the ring is at its bound."""
        with self._lock:
            seg = self._acquire(nbytes)
            if seg is None:
                self.fallbacks += 1
                return None
            try:
                view = seg.view
                assert view is not None
                end = DATA_OFFSET
                for blob in blobs:
                    n = blob.nbytes
                    view[end:end + n] = blob.reshape(-1).view(np.uint8)
                    end += n
                seg.generation += 1
                _SEG_HEADER.pack_into(seg.mm, 0, SEGMENT_MAGIC, seg.generation, nbytes)  # type: ignore[arg-type]
                return msgpack.packb([os.getpid(), seg.fd, seg.ino, seg.generation, nbytes, HOST_ID])
            finally:
                fcntl.flock(seg.fd, fcntl.LOCK_UN)

    def _acquire(self, nbytes: int) -> _Segment | None:
        """A segment of at least nbytes no reader holds, locked exclusively (caller holds self._lock), moved to
        the front. A sealed segment cannot grow: one too small is replaced by a larger one (readers still
        mapping the old one keep their own mapping of it)."""
        now = time.monotonic()
        seg = self._lock_first(s for s in self._segments if now - s.written >= REUSE_AFTER_S)
        if seg is None and len(self._segments) < MAX_SEGMENTS:
            seg = self._new_segment(nbytes)
        if seg is None:
            seg = self._lock_first(reversed(self._segments))  # all young: the oldest free one
        if seg is not None and seg.capacity < nbytes:
            self._segments.remove(seg)
            seg.close()
            seg = self._new_segment(max(nbytes, 2 * seg.capacity))
        if seg is not None:
            seg.written = now
            self._segments.remove(seg)
            self._segments.insert(0, seg)
        return seg

    def _new_segment(self, nbytes: int) -> _Segment:
        seg = _Segment(nbytes)
        fcntl.flock(seg.fd, fcntl.LOCK_EX)
        self._segments.append(seg)
        return seg

    @staticmethod
    def _lock_first(segments: Iterable[_Segment]) -> _Segment | None:
        for seg in segments:
            try:
                fcntl.flock(seg.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue
            return seg
        return None

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._live.undeclare()
        with self._lock:
            for seg in self._segments:
                seg.close()
            self._segments.clear()
            self.ready = False


def frame(descriptor: bytes, head: bytes) -> bytes:
    """The lane message sent over Zenoh: lane prefix, descriptor, then the frame head."""
    return _PREFIX.pack(LANE_MAGIC, len(descriptor)) + descriptor + head


# --- the reader --------------------------------------------------------------------------------------

def is_lane(data: bytes | bytearray | memoryview) -> bool:
    """Whether a payload is a lane message (else an inline frame, or garbage for the decoder to refuse)."""
    return data[:3] == LANE_MAGIC


def split(data: bytes | bytearray | memoryview) -> tuple[Any, memoryview]:
    """(descriptor as decoded, frame head) of a lane message; DecodeError when malformed."""
    if len(data) < _PREFIX.size:
        raise DecodeError("lane message too short")
    magic, n = _PREFIX.unpack_from(data)
    if magic != LANE_MAGIC or n > MAX_DESCRIPTOR_BYTES or _PREFIX.size + n > len(data):
        raise DecodeError("malformed lane descriptor")
    view = memoryview(data)
    try:
        desc = msgpack.unpackb(view[_PREFIX.size:_PREFIX.size + n])
    except Exception as exc:
        raise DecodeError(f"lane descriptor is not msgpack: {exc}") from exc
    return desc, view[_PREFIX.size + n:]


class _Mapped:
    """A segment as this process maps it: one descriptor and one read-only mapping, shared by every message
    read from it, and the shared lock held while any of those messages' arrays live (``refs``)."""

    def __init__(self, name: str, fd: int, ino: int, size: int):
        self.name, self.fd, self.ino, self.size = name, fd, ino, size
        self.mm = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ)
        self.array: np.ndarray | None = np.frombuffer(self.mm, np.uint8)  # read-only: PROT_READ
        self.refs = 0
        self.used = 0.0
        self.evicted = False
        self._watched: dict[int, weakref.ref] = {}  # the weak references whose callbacks release

    def hold(self, start: int, end: int) -> memoryview:
        """A read-only view of bytes start..end for one message (the caller counted it in ``refs``): every
        array decoded from it hangs on this view, whose end releases the message's share of the lock."""
        assert self.array is not None
        view = self.array[start:end]
        ref = weakref.ref(view, self._gone)
        self._watched[id(ref)] = ref
        return memoryview(view)

    def _gone(self, ref: weakref.ref) -> None:
        self._watched.pop(id(ref), None)
        self.release()

    def release(self) -> None:
        with _cache_lock:
            self.refs -= 1
            if self.refs == 0:
                with contextlib.suppress(OSError):
                    fcntl.flock(self.fd, fcntl.LOCK_UN)
                if self.evicted:
                    self._close()

    def _close(self) -> None:
        """Unmap and close (caller holds _cache_lock, refs is 0: no array of ours is left)."""
        self.array = None
        with contextlib.suppress(BufferError, ValueError):
            self.mm.close()
        with contextlib.suppress(OSError):
            os.close(self.fd)

    def evict(self) -> None:
        self.evicted = True
        if self.refs == 0:
            self._close()


_cache: dict[str, _Mapped] = {}
# Re-entrant: a message's arrays may be collected (releasing their segment) by a garbage collection that
# starts while this thread holds the lock.
_cache_lock = threading.RLock()
_last_sweep = 0.0
CACHE_IDLE_S = 2.0  # a segment no message has named this long is unmapped (its publisher may be gone)


def _open_segment(pid: int, fd: int, ino: int, size: int) -> _Mapped:
    """Open another process's segment through /proc, each check that needs no open made before it (see the
    module doc): the process is this user's, its fd names our memfd; then the file itself, pinned by O_PATH."""
    name, path = f"{pid}/{fd}", f"/proc/{pid}/fd/{fd}"
    try:
        owner = os.stat(f"/proc/{pid}").st_uid
        link = os.readlink(path)
    except FileNotFoundError:
        raise LaneStale(f"lane segment {name} is gone") from None
    except OSError as exc:
        raise DecodeError(f"lane segment {name}: {os.strerror(exc.errno or errno.EIO)}") from None
    if owner != os.getuid():
        raise DecodeError(f"lane segment {name}: process {pid} is not this user's")
    if link != _MEMFD_LINK:
        raise DecodeError(f"lane segment {name}: not a followbus memfd")
    pinned = _pin(path, name)
    try:
        _check_pinned(pinned, name, ino)
        rfd = os.open(f"/proc/self/fd/{pinned}", os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    finally:
        os.close(pinned)
    try:
        _check_segment(rfd, name, ino, size)
        return _Mapped(name, rfd, ino, os.fstat(rfd).st_size)
    except BaseException:
        os.close(rfd)
        raise


def _pin(path: str, name: str) -> int:
    """An O_PATH descriptor of the file ``path`` names: it refers to the file without opening it (no driver's
    open runs), so what is checked on it is what a reopen through /proc/self/fd gets."""
    try:
        return os.open(path, os.O_PATH | os.O_CLOEXEC)
    except FileNotFoundError:
        raise LaneStale(f"lane segment {name} is gone") from None
    except OSError as exc:
        raise DecodeError(f"lane segment {name}: {os.strerror(exc.errno or errno.EIO)}") from None


def _check_pinned(pinned: int, name: str, ino: int) -> None:
    """The pinned file is still our memfd (the fd number may have been reused since the readlink), of this user,
    of the inode the descriptor names."""
    st = os.fstat(pinned)
    if os.readlink(f"/proc/self/fd/{pinned}") != _MEMFD_LINK or not stat.S_ISREG(st.st_mode) \
            or st.st_uid != os.getuid():
        raise DecodeError(f"lane segment {name}: not a followbus memfd of this user")
    if st.st_ino != ino:
        raise LaneStale(f"lane segment {name} was replaced")


def _check_segment(fd: int, name: str, ino: int, size: int) -> None:
    """The opened segment: the inode pinned, sealed exactly with SEALS, large enough."""
    st = os.fstat(fd)
    if st.st_ino != ino:
        raise LaneStale(f"lane segment {name} was replaced")
    try:
        seals = fcntl.fcntl(fd, fcntl.F_GET_SEALS)
    except OSError:
        seals = -1
    if seals != SEALS:
        raise DecodeError(f"lane segment {name}: seals {seals:#x}, not {SEALS:#x} (it could be truncated or rewritten)")
    if st.st_size < size:
        raise DecodeError(f"lane segment {name}: {st.st_size} bytes, descriptor names {size}")


def _sweep(now: float) -> None:
    """Unmap segments idle for CACHE_IDLE_S (caller holds _cache_lock)."""
    global _last_sweep
    _last_sweep = now
    for name, mapped in list(_cache.items()):
        if mapped.refs == 0 and now - mapped.used > CACHE_IDLE_S:
            del _cache[name]
            mapped.evict()


def sweep_idle() -> None:
    """Unmap the segments no message has named for CACHE_IDLE_S (called on the receive path of every message,
    so the mappings of a publisher that went away do not outlive it for long): a time check when nothing is due."""
    now = time.monotonic()
    if now - _last_sweep > CACHE_IDLE_S and _cache:
        with _cache_lock:
            _sweep(now)


class _Descriptor(NamedTuple):
    """A lane descriptor that passed :func:`_parse_descriptor` (each number a non-negative int, the host ours)."""

    pid: int
    fd: int
    ino: int
    generation: int
    length: int
    host: str

    @property
    def name(self) -> str:
        return f"{self.pid}/{self.fd}"

    @property
    def size(self) -> int:
        """The segment size the data needs: header, then the data from DATA_OFFSET."""
        return DATA_OFFSET + self.length


def open_blob_area(desc: Any) -> memoryview:
    """A read-only view of the data a descriptor names, the segment locked shared for as long as the view
    (or anything made from it) lives. DecodeError for a descriptor that is not acceptable, LaneStale when
    the data was overwritten or removed since.

    A segment stays mapped between messages (no open, mmap and page-table set-up per message) while
    descriptors name it with the same inode and size; a cached mapping whose generation does not match is
    dropped and the name opened afresh once (its file may have been replaced under the same name)."""
    lane = _parse_descriptor(desc)
    now = time.monotonic()
    while True:
        mapped, fresh = _lock_mapping(lane, now)
        magic, gen, written = _SEG_HEADER.unpack_from(mapped.mm)
        if magic == SEGMENT_MAGIC and gen == lane.generation and written == lane.length:
            return mapped.hold(DATA_OFFSET, lane.size)
        mapped.release()
        if magic != SEGMENT_MAGIC:
            raise DecodeError(f"lane segment {lane.name}: bad magic")
        if fresh:
            raise LaneStale(f"lane segment {lane.name} was rewritten (generation {gen}, wanted {lane.generation})")
        _forget_mapping(lane.name, mapped)


def _parse_descriptor(desc: Any) -> _Descriptor:
    """The untrusted descriptor checked for shape, range and host before anything is looked at (DecodeError)."""
    if not (isinstance(desc, list) and len(desc) == 6):
        raise DecodeError("lane descriptor: expected [pid, fd, inode, generation, length, host id]")
    lane = _Descriptor(*desc)
    numbers = desc[:5]
    if not all(type(v) is int and v >= 0 for v in numbers) or lane.length > MAX_LANE_BYTES or lane.pid == 0:
        raise DecodeError("lane descriptor: bad pid, fd, inode, generation or length")
    if lane.host != HOST_ID:
        raise DecodeError(f"lane descriptor from host {lane.host!r}, not this one: its pid names none of ours")
    return lane


def _lock_mapping(lane: _Descriptor, now: float) -> tuple[_Mapped, bool]:
    """The mapping of the segment ``lane`` names (cached, else opened and checked), locked shared and
    counted as held by one more message; and whether it was opened just now."""
    with _cache_lock:
        if now - _last_sweep > CACHE_IDLE_S:
            _sweep(now)
        mapped = _cached_mapping(lane)
        fresh = mapped is None
        if mapped is None:
            mapped = _cache[lane.name] = _open_segment(lane.pid, lane.fd, lane.ino, lane.size)
        mapped.used = now
        if mapped.refs == 0:  # else another message of ours holds it: no writer can have it
            try:
                fcntl.flock(mapped.fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                raise LaneStale(f"lane segment {lane.name} is being rewritten") from None
        mapped.refs += 1
    return mapped, fresh


def _cached_mapping(lane: _Descriptor) -> _Mapped | None:
    """The cached mapping of ``lane``'s name if it is of the same inode and large enough; a mismatching one is
    dropped (caller holds _cache_lock)."""
    mapped = _cache.get(lane.name)
    if mapped is not None and (mapped.ino != lane.ino or mapped.size < lane.size):
        del _cache[lane.name]
        mapped.evict()
        return None
    return mapped


def _forget_mapping(name: str, mapped: _Mapped) -> None:
    """Drop ``mapped`` from the cache unless another message already replaced it there."""
    with _cache_lock:
        if _cache.get(name) is mapped:
            del _cache[name]
            mapped.evict()


def materialize(data: bytes | bytearray | memoryview) -> bytes:
    """The inline frame (head and blob area joined, a private copy) a lane message stands for: what a tool
    that keeps or forwards raw bytes (record, echo, bridges) needs. DecodeError / LaneStale as above."""
    desc, head = split(data)
    area = open_blob_area(desc)
    return b"".join([head, area])

