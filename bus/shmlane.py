"""The same-host lane: large arrays in followbus's own shared memory, a small descriptor over Zenoh.

zenoh-python 1.10 gives a received ``ZBytes``/``ZShm`` no buffer protocol, so a receiver must copy every
payload out of Zenoh's shared memory. For large arrays between processes on the same machine this module
carries the array bytes outside Zenoh instead, where the receiver can map them without a copy:

* Writer (:class:`LaneWriter`, one per :class:`~.pubsub.Publisher`): segment files
  ``/dev/shm/followbus-<host id>-<pid>-<n>`` (tmpfs, mode 0600), each mmapped by the publisher for its
  lifetime. A segment is rewritten only under ``flock(LOCK_EX | LOCK_NB)`` and no sooner than
  :data:`REUSE_AFTER_S` after its last write; the writer takes the most recently written free one (its pages
  are still cached), else creates one (up to :data:`MAX_SEGMENTS`), and with all held by readers answers
  None (the publisher then sends the message inline, as without a lane). Every write bumps the segment's
  generation. Segments only grow, and are unlinked when the publisher undeclares or the process exits;
  those of a killed process are removed by the next lane publisher of this host (:func:`clean_stale_segments`).
* Wire form (:data:`LANE_MAGIC`): ``b"FBL" | u32 N | msgpack [segment name, inode, generation, length] (N
  bytes) | the message's frame head`` (bus/codec.py: magic, head length, msgpack map); the head's
  out-of-band array references point into the segment's data instead of a blob area after the head.
* Reader (:func:`open_blob_area`): the descriptor is untrusted. Only names of the followbus pattern with this
  host's id, opened directly under /dev/shm without following links, regular files of this user, of the
  inode named, large enough; then ``flock(LOCK_SH | LOCK_NB)``, a read-only mapping (kept between messages),
  magic, generation and length. Decoded arrays are read-only numpy views of that mapping; the shared lock is
  held until the last array of the message is gone, so a received array stays valid and unchanged after the
  handler returns, as for an inline message. A segment rewritten or removed since the descriptor was sent
  raises :class:`LaneStale` (a drop); anything else wrong, DecodeError (a decode error).
* Who gets descriptors: every followbus subscription declares a liveliness token
  ``@followbus/lane/<host id>/<unique id>/<key expression, hex>`` (:func:`declare_token`) before its
  subscriber. A lane publisher follows those tokens (``LaneWriter.ready``) and writes to the lane only while
  at least one token matches its key and every matching token carries its own host id (boot id, /dev/shm's
  device and inode, pid namespace, user); anything else (a subscriber on another machine, in a container
  with its own /dev/shm or pids, of another user) makes it publish inline, to everyone. A plain Zenoh
  subscriber that declares no token cannot be seen: it gets descriptors while a followbus subscriber on the
  same host shares the key (README, Messages); ``zenoh: shm_lane: false`` turns the lane off.

bus/ knows nothing of tracking: this module moves bytes.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import fcntl
import hashlib
import itertools
import logging
import mmap
import os
import re
import secrets
import stat
import struct
import threading
import time
import weakref
from collections.abc import Iterable
from typing import Any

import msgpack
import numpy as np

from .codec import DecodeError

log = logging.getLogger(__name__)

SHM_DIR = "/dev/shm"
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
_NAME = re.compile(r"followbus-([0-9a-f]{16})-([0-9]{1,10})-([0-9]{1,10})")  # host id, pid, number
_counter = itertools.count()
_own_paths: set[str] = set()
_own_lock = threading.Lock()
_cleaned = False


class LaneStale(DecodeError):
    """The segment was rewritten (or removed) since the descriptor was sent: the message is gone."""


# --- where we are ------------------------------------------------------------------------------------

def _compute_host_id() -> str | None:
    """Who can read our segments and see our pids: the boot id, the device and inode of /dev/shm, the pid
    namespace and the user, hashed (a container with its own /dev/shm or pids, another user: another
    "host", served inline). None when there is no usable /dev/shm (the lane is then off)."""
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            boot = f.read().strip()
        st = os.stat(SHM_DIR)
        if not stat.S_ISDIR(st.st_mode) or not os.access(SHM_DIR, os.W_OK):
            return None
        pid_ns = os.readlink("/proc/self/ns/pid")
    except OSError:
        return None
    return hashlib.sha256(f"{boot}:{st.st_dev}:{st.st_ino}:{pid_ns}:{os.getuid()}".encode()).hexdigest()[:16]


HOST_ID = _compute_host_id()


INLINE_HOST = "inline"  # a token's host for a subscription that wants every message inline (see declare_token)


def token_key(key_expr: str, *, inline: bool = False) -> str:
    """A fresh liveliness token key announcing a followbus subscription of ``key_expr`` on this host (or one
    that wants inline messages: no host's id, so publishers of the key go inline while it is there)."""
    host = INLINE_HOST if inline else (HOST_ID or "nolane")
    return f"{TOKEN_PREFIX}/{host}/{secrets.token_hex(8)}/{key_expr.encode().hex()}"


def declare_token(session: Any, key_expr: str, *, inline: bool = False) -> Any:
    """Declare this subscription's lane token (before its subscriber); None if Zenoh refused it.

    ``inline``: the subscription must get every message, however long it stalls (the recorder). A segment is
    rewritten one frame period after its last write, so a reader that stalls longer finds the frames it
    missed gone (counted as drops): a live consumer wants the newest frame anyway, a recording wants them
    all. Such a token makes the publishers of the key send inline, to everyone, while it is declared."""
    try:
        return session.liveliness().declare_token(token_key(key_expr, inline=inline))
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

def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_stale_segments() -> int:
    """Remove the segments of followbus processes that are gone (a crashed publisher leaves its segments).
    A reader still mapping one keeps its mapping (unlinking only removes the name)."""
    removed = 0
    try:
        names = os.listdir(SHM_DIR)
    except OSError:
        return 0
    me = os.getuid()
    for name in names:
        m = _NAME.fullmatch(name)
        # Only segments named with our host id: their pids are in our pid namespace.
        if m is None or m.group(1) != HOST_ID or _pid_alive(int(m.group(2))):
            continue
        path = os.path.join(SHM_DIR, name)
        try:
            if os.lstat(path).st_uid != me:
                continue
            os.unlink(path)
            removed += 1
        except OSError:
            continue
    if removed:
        log.info("removed %d shared-memory lane segment(s) of ended processes", removed)
    return removed


def _unlink_own() -> None:
    with _own_lock:
        paths = list(_own_paths)
        _own_paths.clear()
    for path in paths:
        with contextlib.suppress(OSError):
            os.unlink(path)


atexit.register(_unlink_own)


class _Segment:
    def __init__(self) -> None:
        self.name = f"followbus-{HOST_ID}-{os.getpid()}-{next(_counter)}"
        self.path = os.path.join(SHM_DIR, self.name)
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
        with _own_lock:
            _own_paths.add(self.path)
        self.ino = os.fstat(self.fd).st_ino
        self.capacity = 0
        self.mm: mmap.mmap | None = None
        self.view: np.ndarray | None = None
        self.generation = secrets.randbits(48)
        self.written = 0.0  # time.monotonic() of the last write

    def reserve(self, nbytes: int) -> None:
        """Room for nbytes of data. Segments only grow: a reader's mapping of the old size stays valid."""
        if nbytes <= self.capacity:
            return
        capacity = max(nbytes, 2 * self.capacity)
        capacity = -(-capacity // 65536) * 65536
        os.ftruncate(self.fd, DATA_OFFSET + capacity)
        self.view = None
        if self.mm is not None:
            self.mm.close()
        self.mm = mmap.mmap(self.fd, DATA_OFFSET + capacity, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        self.view = np.frombuffer(self.mm, np.uint8)
        self.capacity = capacity

    def close(self) -> None:
        self.view = None
        if self.mm is not None:
            self.mm.close()
            self.mm = None
        os.close(self.fd)
        with contextlib.suppress(OSError):
            os.unlink(self.path)
        with _own_lock:
            _own_paths.discard(self.path)


class LaneWriter:
    """One publisher's ring of segments and its view of who subscribes to its key (see the module doc)."""

    def __init__(self, session: Any, key: str):
        global _cleaned
        if HOST_ID is None:
            raise OSError("no usable /dev/shm")
        if not _cleaned:
            _cleaned = True
            clean_stale_segments()
        import zenoh

        self.key = key
        self._key_expr = zenoh.KeyExpr(key)
        self._segments: list[_Segment] = []  # most recently written first
        self._lock = threading.Lock()
        self._tokens: dict[str, bool] = {}  # token key -> whether it is a subscriber of our key on this host
        self.ready = False  # every known subscriber of the key is a followbus one on this host
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
            else:
                self._tokens[key] = host == HOST_ID
            self.ready = bool(self._tokens) and all(self._tokens.values())

    def write(self, blobs: list[np.ndarray], nbytes: int) -> bytes | None:
        """Write the arrays one after the other into a free segment; the descriptor (msgpack), or None when
        every segment is held by readers and the ring is at its bound."""
        with self._lock:
            seg = self._acquire()
            if seg is None:
                self.fallbacks += 1
                return None
            try:
                seg.reserve(nbytes)
                view = seg.view
                assert view is not None
                end = DATA_OFFSET
                for blob in blobs:
                    n = blob.nbytes
                    view[end:end + n] = blob.reshape(-1).view(np.uint8)
                    end += n
                seg.generation += 1
                _SEG_HEADER.pack_into(seg.mm, 0, SEGMENT_MAGIC, seg.generation, nbytes)  # type: ignore[arg-type]
                return msgpack.packb([seg.name, seg.ino, seg.generation, nbytes])
            finally:
                fcntl.flock(seg.fd, fcntl.LOCK_UN)

    def _acquire(self) -> _Segment | None:
        """A segment no reader holds, locked exclusively (caller holds self._lock), moved to the front."""
        now = time.monotonic()
        seg = self._lock_first(s for s in self._segments if now - s.written >= REUSE_AFTER_S)
        if seg is None and len(self._segments) < MAX_SEGMENTS:
            seg = _Segment()
            fcntl.flock(seg.fd, fcntl.LOCK_EX)
            self._segments.append(seg)
        if seg is None:
            seg = self._lock_first(reversed(self._segments))  # all young: the oldest free one
        if seg is not None:
            seg.written = now
            self._segments.remove(seg)
            self._segments.insert(0, seg)
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


def _open_segment(name: str, ino: int, size: int) -> _Mapped:
    path = os.path.join(SHM_DIR, name)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise LaneStale(f"lane segment {name} is gone") from None
    except OSError as exc:
        raise DecodeError(f"lane segment {name}: {os.strerror(exc.errno or errno.EIO)}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_uid != os.getuid():
            raise DecodeError(f"lane segment {name}: not a regular file of this user")
        if st.st_ino != ino:
            raise LaneStale(f"lane segment {name} was replaced")
        if st.st_size < size:
            raise DecodeError(f"lane segment {name}: {st.st_size} bytes, descriptor names {size}")
        return _Mapped(name, fd, ino, st.st_size)
    except BaseException:
        os.close(fd)
        raise


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


def open_blob_area(desc: Any) -> memoryview:
    """A read-only view of the data a descriptor names, the segment locked shared for as long as the view
    (or anything made from it) lives. DecodeError for a descriptor that is not acceptable, LaneStale when
    the data was overwritten or removed since.

    A segment stays mapped between messages (no open, mmap and page-table set-up per message) while
    descriptors name it with the same inode and size; a cached mapping whose generation does not match is
    dropped and the name opened afresh once (its file may have been replaced under the same name)."""
    if not (isinstance(desc, list) and len(desc) == 4):
        raise DecodeError("lane descriptor: expected [name, inode, generation, length]")
    name, ino, generation, length = desc
    m = _NAME.fullmatch(name) if isinstance(name, str) else None
    if m is None:
        raise DecodeError("lane descriptor: not a followbus segment name")
    if m.group(1) != HOST_ID:
        raise DecodeError("lane descriptor: a segment of another host")
    if not all(type(v) is int and v >= 0 for v in (ino, generation, length)) or length > MAX_LANE_BYTES:
        raise DecodeError("lane descriptor: bad inode, generation or length")
    size = DATA_OFFSET + length
    now = time.monotonic()
    while True:
        with _cache_lock:
            if now - _last_sweep > CACHE_IDLE_S:
                _sweep(now)
            mapped = _cache.get(name)
            if mapped is not None and (mapped.ino != ino or mapped.size < size):
                del _cache[name]
                mapped.evict()
                mapped = None
            fresh = mapped is None
            if mapped is None:
                mapped = _cache[name] = _open_segment(name, ino, size)
            mapped.used = now
            if mapped.refs == 0:  # else another message of ours holds it: no writer can have it
                try:
                    fcntl.flock(mapped.fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
                except BlockingIOError:
                    raise LaneStale(f"lane segment {name} is being rewritten") from None
            mapped.refs += 1
        magic, gen, written = _SEG_HEADER.unpack_from(mapped.mm)
        if magic == SEGMENT_MAGIC and gen == generation and written == length:
            return mapped.hold(DATA_OFFSET, size)
        mapped.release()
        if magic != SEGMENT_MAGIC:
            raise DecodeError(f"lane segment {name}: bad magic")
        if fresh:
            raise LaneStale(f"lane segment {name} was rewritten (generation {gen}, wanted {generation})")
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

