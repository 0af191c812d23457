"""Publishers and subscribers over Zenoh with typed messages, SHM for large local payloads,
per-topic congestion control, bounded input queues and decode-error accounting."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from . import shmlane
from .codec import DecodeError
from .schemas import Message, decode, encode_parts, validate
from .stats import SequenceGaps, TopicStats

log = logging.getLogger(__name__)

SHM_THRESHOLD_BYTES = 64 * 1024
SHM_POOL_BYTES = 64 * 1024 * 1024
SHM_RETRY_S = 5.0  # after a failed shared-memory allocation, large payloads go inline this long, then retry
LOST_WARN_PERIOD_S = 10.0  # a subscriber says at most this often that messages never reached it
CONGESTION = {"block": zenoh.CongestionControl.BLOCK, "drop": zenoh.CongestionControl.DROP}
# Zenoh queues each priority separately on a link: a "real_time" message is not stuck behind a backlog of
# "data" ones (frames, a flood of bad payloads), which is what a stop command needs.
PRIORITY = {"real_time": zenoh.Priority.REAL_TIME, "interactive_high": zenoh.Priority.INTERACTIVE_HIGH,
            "data": zenoh.Priority.DATA}
# A Publisher refuses (counts in TopicStats.refused, logs, does not send) payloads over this. Zenoh 1.10's
# own limit is the receiver's transport/link/rx/max_message_size, 1 GiB by default: past it a message
# vanishes with no error at either end. Far below that, a payload larger than the shared-memory pool
# (SHM_POOL_BYTES) cannot use it, and with congestion "drop" large fragmented puts are dropped too from 32 MiB
# on (RELIABILITY.md, incidents behind the code).
# The largest payload the graph means to send, a 4K bgr8 frame, is 24.9 MB.
MAX_PAYLOAD_BYTES = 48 * 1024 * 1024


def direct_callback(fn: Callable[[zenoh.Sample], Any]) -> Any:
    """A Zenoh subscriber handler that runs ``fn`` on the thread that received the sample.

    zenoh-python's default for a plain function hands every sample to a callback thread of its own per
    subscriber. That loses the order of samples across keys (replay determinism), and those threads can
    still be delivering into Python while the interpreter shuts down, which aborts the process ("FATAL:
    exception not rethrown", exit -6; seen for `monitor --once` under load, 3 of 20 runs, 0 of 45 with
    direct callbacks). Callbacks given this way must be quick: decode, copy, return.
    """
    return zenoh.handlers.Callback(fn, indirect=False)


class RateLimitedLog:
    """Log a recurring problem at most once per period, with the count of suppressed repeats."""

    def __init__(self, logger: logging.Logger, period_s: float = 1.0):
        self.logger = logger
        self.period_s = period_s
        self._last = 0.0
        self._suppressed = 0
        self._lock = threading.Lock()

    def warning(self, msg: str, *args: Any) -> None:
        now = time.monotonic()
        with self._lock:
            if now - self._last < self.period_s:
                self._suppressed += 1
                return
            suppressed, self._suppressed, self._last = self._suppressed, 0, now
        suffix = f" (+{suppressed} similar in the last {self.period_s:.0f} s)" if suppressed else ""
        self.logger.warning(msg + suffix, *args)


class ShmPool:
    """Lazily created shared-memory provider shared by a process's publishers.

    A failed allocation (no /dev/shm, /dev/shm full, pool exhausted) sends that payload over the network path
    and is tried again :data:`SHM_RETRY_S` later, never turned off for good: /dev/shm filled by something else
    for a while must not cost the rest of the process's life."""

    def __init__(self, size_bytes: int = SHM_POOL_BYTES):
        self.size_bytes = size_bytes
        self._provider: Any = None
        self._retry_at = 0.0  # time.monotonic() before which shared memory is not tried again
        self.failures = 0
        self._lock = threading.Lock()

    def _alloc(self, n: int) -> Any | None:
        """A buffer of n bytes (caller holds the lock); None while shared memory is unusable."""
        if time.monotonic() < self._retry_at:
            return None
        try:
            import zenoh.shm as zshm

            if self._provider is None:
                self._provider = zshm.ShmProvider.default_backend(self.size_bytes)
            return self._provider.alloc(n, zshm.GarbageCollect(zshm.Defragment()))
        except Exception as exc:  # no /dev/shm, pool exhausted, ...: fall back to plain bytes for a while
            self.failures += 1
            if self.failures == 1 or self.failures % 100 == 0:
                log.warning("shared memory unavailable (%s); publishing large payloads over the network path, "
                            "trying again in %.0f s (%d failures)", exc, SHM_RETRY_S, self.failures)
            self._retry_at = time.monotonic() + SHM_RETRY_S
            return None

    def warm_up(self) -> None:
        """Create the pool now. Creating it takes ~50 ms (and the first allocation a few more): on the first
        large publish that would delay frame 0 so much that frame 1 follows right behind it, and a consumer
        with a one-frame queue (detection) would drop frame 0."""
        with self._lock:
            self._alloc(SHM_THRESHOLD_BYTES)  # the buffer is released when it goes out of scope

    def buffer_with(self, payload: bytes | bytearray) -> Any | None:
        """A shared-memory buffer holding a copy of ``payload``; None when shared memory is unusable."""
        with self._lock:
            buf = self._alloc(len(payload))
        if buf is None:
            return None
        buf[:] = payload
        return buf

    def buffer_with_parts(self, head: bytes, blobs: list[np.ndarray]) -> Any | None:
        """A shared-memory buffer holding a frame written in place: ``head``, then each blob's bytes.

        zenoh-python 1.10 (its cp39-abi3 wheel) writes into a ``ZShmMut`` only from ``bytes`` or
        ``bytearray`` (no buffer protocol: neither memoryview nor numpy can fill it), so an array backed by a
        bytearray it covers whole (a camera buffer, ``np.frombuffer(bytearray)``) is copied once, from that
        bytearray; any other array needs ``tobytes()`` first: a second copy, forced by the binding.
        """
        total = len(head) + sum(b.nbytes for b in blobs)
        with self._lock:
            buf = self._alloc(total)
        if buf is None:
            return None
        end = len(head)
        buf[:end] = head
        for blob in blobs:
            buf[end:end + blob.nbytes] = _byte_source(blob)
            end += blob.nbytes
        return buf


def _byte_source(arr: np.ndarray) -> bytes | bytearray:
    """The bytes of a C-contiguous array as something ``ZShmMut`` accepts, without a copy when possible."""
    owner: Any = arr
    while isinstance(owner, np.ndarray):
        owner = owner.base
    if isinstance(owner, memoryview):
        owner = owner.obj
    if (isinstance(owner, (bytes, bytearray)) and len(owner) == arr.nbytes
            and np.frombuffer(owner, np.uint8).ctypes.data == arr.ctypes.data):
        return owner
    return arr.tobytes()


class Publisher:
    """Publishes typed messages on one key. Fills header.seq, header.source and header.pub_ns.

    A payload over ``max_payload_bytes`` is refused: counted in ``stats.refused`` (so it shows in the
    node's status), logged at most every 5 s, and ``put`` returns False instead of raising, so one
    oversized output costs that message only, not the rest of the node's handler. A refused message
    keeps its ``header.seq``: subscribers see the gap, as for any message lost on the way.
    """

    def __init__(self, session: zenoh.Session, key: str, source: str, *, congestion: str = "block",
                 express: bool = False, priority: str = "data", shm: ShmPool | None = None,
                 stats: TopicStats | None = None, max_payload_bytes: int = MAX_PAYLOAD_BYTES,
                 lane: bool = False):
        if congestion not in CONGESTION:
            raise ValueError(f"congestion must be one of {sorted(CONGESTION)}")
        if priority not in PRIORITY:
            raise ValueError(f"priority must be one of {sorted(PRIORITY)}")
        self.key = key
        self.source = source
        self.shm = shm
        self.stats = stats or TopicStats(key, "out")
        self.max_payload_bytes = max_payload_bytes
        self._seq = 0
        self._warn = RateLimitedLog(log, 5.0)
        opts = dict(congestion_control=CONGESTION[congestion], express=express, priority=PRIORITY[priority])
        self._pub = session.declare_publisher(key, **opts)
        self._pub_matched = MatchingFlag(self._pub)
        # Lane subscribers (bus/shmlane.py) take this key's messages on its side key: descriptors when the lane
        # is on and every one of them is on this host, else the message itself. Each key gets a put only while
        # Zenoh's matching status says someone subscribes there, so a plain subscriber of the real key (no
        # token: another program, a bridge, the recorder) always receives the real message.
        self._side = session.declare_publisher(shmlane.side_key(key), **opts)
        self._side_matched = MatchingFlag(self._side)
        self._session = session
        self._lane: shmlane.LaneWriter | None = None  # set up on the first message large enough for it
        self._lane_wanted = lane
        self._lane_warn = RateLimitedLog(log, 30.0)

    def put(self, msg: Message) -> bool:
        """Publish ``msg``; False when it was refused for its size. Never raises for the lane: any lane
        problem sends the message inline."""
        msg.header.seq = self._seq
        msg.header.source = self.source
        msg.header.pub_ns = time.time_ns()
        self._seq += 1
        head, blobs = encode_parts(msg)
        size = len(head) + sum(b.nbytes for b in blobs)
        if not self._fits(size):
            return False
        if self._side_matched.value:
            self._side.put(self._lane_body(head, blobs, size) or self._inline_body(head, blobs, size))
        if self._pub_matched.value:
            self._pub.put(self._inline_body(head, blobs, size))
        self.stats.record(msg.header.stamp_ns, size)
        return True

    def _inline_body(self, head: bytes, blobs: list[np.ndarray], size: int) -> Any:
        if self.shm is not None and size >= SHM_THRESHOLD_BYTES:
            # Header and arrays written straight into the shared-memory buffer: no joined frame in between.
            body = self.shm.buffer_with_parts(head, blobs)
            if body is not None:
                return body
        return head if not blobs else b"".join([head, *(memoryview(b).cast("B") for b in blobs)])

    def _lane_body(self, head: bytes, blobs: list[np.ndarray], size: int) -> bytes | None:
        """The lane message (descriptor and head) for the side key, or None: send it inline."""
        if not self._lane_wanted or size - len(head) < shmlane.LANE_THRESHOLD_BYTES:
            return None
        try:
            lane = self._lane or self._open_lane()
            if lane is None or not lane.ready:
                return None
            desc = lane.write(blobs, size - len(head))
        except Exception as exc:  # no memfd, out of memory, ...: inline this time, try again next time
            self._lane_warn.warning("shared-memory lane write failed on %s (%r); sending inline", self.key, exc)
            return None
        return None if desc is None else shmlane.frame(desc, head)

    def _open_lane(self) -> shmlane.LaneWriter | None:
        try:
            self._lane = shmlane.LaneWriter(self._session, self.key)
        except Exception as exc:  # no /dev/shm, ...: the lane stays off, payloads go inline
            log.warning("shared-memory lane unavailable for %s (%s); publishing inline", self.key, exc)
            self._lane_wanted = False
        return self._lane

    @property
    def listened(self) -> bool:
        """Whether anyone subscribes to the key (its lane side key included): else put sends nothing."""
        return self._side_matched.value or self._pub_matched.value

    @property
    def lane_fallbacks(self) -> int:
        """Messages that went inline because every lane segment was held by readers."""
        return self._lane.fallbacks if self._lane is not None else 0

    def put_bytes(self, payload: bytes, stamp_ns: int = 0) -> bool:
        """Publish an already encoded payload (recording playback); False when it was refused for its size."""
        if not self._fits(len(payload)):
            return False
        for pub, matched in ((self._side, self._side_matched), (self._pub, self._pub_matched)):
            if matched.value:
                body: Any = payload
                if self.shm is not None and len(payload) >= SHM_THRESHOLD_BYTES:
                    body = self.shm.buffer_with(payload) or payload
                pub.put(body)
        self.stats.record(stamp_ns, len(payload))
        return True

    def _fits(self, size: int) -> bool:
        if size <= self.max_payload_bytes:
            return True
        self.stats.refuse()
        self._warn.warning("refused a %.1f MB message on %s: over the %.1f MB publication limit",
                           size / 1e6, self.key, self.max_payload_bytes / 1e6)
        return False

    def undeclare(self) -> None:
        self._pub_matched.undeclare()
        self._side_matched.undeclare()
        self._pub.undeclare()
        self._side.undeclare()
        if self._lane is not None:
            self._lane.close()
            self._lane = None


class MatchingFlag:
    """Whether any subscriber (this session's included) listens to a publisher's key, kept up to date by Zenoh's
    matching listener rather than asked on every put.

    Asking (``matching_status``) walks the session's routing tables: with the graph's peers, about a third of the
    CPU of a node publishing small messages at 100 Hz, two keys a message (RELIABILITY.md, incidents). The
    listener is told on every change, on Zenoh's thread, as soon as ``matching_status`` itself would say so
    (loopback: both within the same 0.1 ms); the status is read once at declaration for the subscribers already
    there.
    """

    def __init__(self, pub: Any):
        self._lock = threading.Lock()
        self._told = False  # a change was reported: it is newer than the status read at declaration
        self.value = True
        self._listener: Any = None
        try:
            self._listener = pub.declare_matching_listener(direct_callback(self._on_change))
        except Exception:  # a closing session: put anyway, as _matching does
            return
        current = _matching(pub)
        with self._lock:
            if not self._told:
                self.value = current

    def _on_change(self, status: Any) -> None:
        with self._lock:
            self._told = True
            self.value = bool(status.matching)

    def undeclare(self) -> None:
        if self._listener is not None:
            with contextlib.suppress(Exception):
                self._listener.undeclare()
            self._listener = None


def _matching(pub: Any) -> bool:
    """Whether any subscriber (this session's included) listens to a publisher's key."""
    try:
        return bool(pub.matching_status.matching)
    except Exception:  # a closing session: put anyway, as before matching was asked
        return True


def payload_bytes(sample: zenoh.Sample) -> bytes:
    """A private copy of a sample's payload (one memcpy out of shared memory for large ones).

    The copy is forced by the binding: zenoh-python 1.10's wheel (cp39-abi3) gives ``ZBytes`` and ``ZShm``
    no buffer protocol, so Python cannot view a received buffer in place (the upstream source exposes one
    only in builds for Python >= 3.11). It also settles the node contract: arrays decoded from it
    (read-only numpy views of this copy) never alias memory Zenoh may reuse, so a node may keep them after
    its handler returns (2.76 MB: ~0.19 ms on the 2-core VM, BENCHMARKS.md).
    """
    payload = sample.payload
    shm_buf = payload.as_shm()
    return bytes(shm_buf) if shm_buf is not None else payload.to_bytes()


def frame_bytes(sample: zenoh.Sample) -> bytes:
    """:func:`payload_bytes`, with a lane message (bus/shmlane.py) turned into the inline frame it stands for:
    what a tool that keeps or forwards the bytes of any message needs (record, echo, bridges; a recording
    never holds a descriptor). Raises DecodeError when a lane message cannot be read (another machine's,
    overwritten, forged): the caller drops it like any malformed payload."""
    data = payload_bytes(sample)
    return shmlane.materialize(data) if shmlane.is_lane(data) else data


class _Tokened:
    """A Zenoh subscriber; a lane one (bus/shmlane.py) subscribes to the key's side key and declares the token
    announcing it first. Undeclared together."""

    def __init__(self, session: zenoh.Session, key: str, handler: Any, *, lane: bool = False):
        self._token = shmlane.declare_token(session, key) if lane else None  # before the subscriber
        self._sub = session.declare_subscriber(shmlane.side_key(key) if lane else key, handler)

    def undeclare(self) -> None:
        self._sub.undeclare()
        if self._token is not None:
            self._token.undeclare()


def declare_subscriber(session: zenoh.Session, key: str, fn: Callable[[zenoh.Sample], Any], *,
                       lane: bool = False) -> Any:
    """A direct-callback Zenoh subscriber for a tool that reads payloads with :func:`frame_bytes`. A plain one
    gets the real messages of the key (every one, however long it stalls: what the recorder needs); with
    ``lane`` (the graph's ``zenoh: shm_lane``) it takes them on the side key, as descriptors from publishers on
    this host (bus/shmlane.py)."""
    return _Tokened(session, key, direct_callback(fn), lane=lane)


class Subscriber:
    """Decodes and validates every sample on a key; malformed ones (bad bytes, wrong type, non-finite or
    out-of-range values) are counted in ``decode_errors``, logged once a second and dropped. Messages that never
    arrived (gaps in a publisher's ``header.seq``: a link that dropped them) are counted in ``stats.lost`` and
    logged at most every :data:`LOST_WARN_PERIOD_S`, so a node that misses frames says so, not only its rate."""

    def __init__(self, session: zenoh.Session, key: str, on_message: Callable[[Message], None], *,
                 schema: type[Message] | None = None, stats: TopicStats | None = None,
                 logger: logging.Logger | None = None, lane: bool = False):
        self.key = key
        self.schema = schema
        self.on_message = on_message
        self.stats = stats or TopicStats(key, "in")
        self._warn = RateLimitedLog(logger or log)
        self._lost_warn = RateLimitedLog(logger or log, LOST_WARN_PERIOD_S)
        self._gaps = SequenceGaps()
        # A direct callback runs on Zenoh's receive thread, so messages on different keys reach the node
        # in the order they arrived (the default indirect callbacks run one thread per subscriber and
        # reorder them: a lockstep replay then diverges). The work here is a decode and an enqueue.
        # ``lane``: take the key's messages on its side key, announced by a lane token (declared first), so a
        # publisher on this host may send large arrays through bus/shmlane.py: the decoded arrays are then
        # read-only views of its segment.
        self._sub = _Tokened(session, key, direct_callback(self._callback), lane=lane)

    def _callback(self, sample: zenoh.Sample) -> None:
        try:
            data = payload_bytes(sample)
            if shmlane.is_lane(data):
                desc, head = shmlane.split(data)
                area = shmlane.open_blob_area(desc)
                msg = validate(decode(head, self.schema, area))
                size = len(head) + len(area)
                del area
            else:
                shmlane.sweep_idle()
                msg = validate(decode(data, self.schema))
                size = len(data)
        except shmlane.LaneStale as exc:
            self.stats.drop()
            self._warn.warning("dropped a message on %s: %s", sample.key_expr, exc)
            return
        except DecodeError as exc:
            self.stats.decode_error()
            self._warn.warning("dropped malformed message on %s: %s", sample.key_expr, exc)
            return
        except Exception as exc:  # never let a bad sample kill zenoh's callback thread
            self.stats.decode_error()
            self._warn.warning("dropped unreadable sample on %s: %r", sample.key_expr, exc)
            return
        self.stats.record(msg.header.stamp_ns, size)
        missing = self._gaps.see(msg.header.source, msg.header.seq)
        if missing > 0:
            self.stats.lose(missing)
            self._lost_warn.warning("%d messages on %s from %s never arrived (header.seq %d after %d; %d lost so far)",
                                    missing, self.key, msg.header.source, msg.header.seq,
                                    msg.header.seq - missing - 1, self.stats.lost)
        self.on_message(msg)

    def undeclare(self) -> None:
        self._sub.undeclare()


class InputQueue:
    """A bounded queue between Zenoh's callback thread and a node's main loop.

    ``drop_oldest`` keeps the newest messages (live video); ``block`` makes the producer wait for
    room (control and recording paths), up to ``block_timeout_s`` so shutdown never deadlocks.
    ``wakes``: a message notifies the consumer at once; False (a node's input read by stamp): only once the queue is
    half full, else it waits for the consumer's next wake-up (the consumer bounds its waits).
    """

    def __init__(self, name: str, maxlen: int, policy: str, stats: TopicStats, wakeup: threading.Condition,
                 block_timeout_s: float = 2.0, wakes: bool = True):
        if policy not in ("drop_oldest", "block"):
            raise ValueError(f"unknown queue policy {policy!r}")
        self.name = name
        self.maxlen = maxlen
        self.policy = policy
        self.stats = stats
        self.block_timeout_s = block_timeout_s
        self.wakes = wakes
        self._items: deque[Message] = deque()
        self._cond = wakeup

    def push(self, msg: Message) -> None:
        with self._cond:
            if len(self._items) >= self.maxlen:
                if self.policy == "drop_oldest":
                    self._items.popleft()
                    self.stats.drop()
                else:
                    deadline = time.monotonic() + self.block_timeout_s
                    while len(self._items) >= self.maxlen:
                        remaining = deadline - time.monotonic()
                        if remaining <= 0:
                            self.stats.drop()
                            return
                        self._cond.wait(remaining)
            self._items.append(msg)
            if self.wakes or 2 * len(self._items) >= self.maxlen:
                self._cond.notify_all()

    def pop_all(self) -> list[Message]:
        """Take everything queued (caller holds the condition)."""
        items = list(self._items)
        self._items.clear()
        return items

    def __len__(self) -> int:
        return len(self._items)
