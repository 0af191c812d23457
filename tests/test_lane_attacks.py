"""The same-host lane against a local process (issue 25 item 2, issue 23 item 2): segments whose names could be
squatted or left stale with a reused pid, truncated under their readers (SIGBUS), or rewritten after the store;
forged descriptors; and a plain Zenoh subscriber that declares no token must get real frames, not descriptors."""

from __future__ import annotations

import contextlib
import ctypes
import mmap
import os
import stat
import struct
import subprocess
import sys
import time

import msgpack
import numpy as np
import pytest

from followbus.bus import shmlane
from followbus.bus.codec import MAGIC
from followbus.bus.pubsub import Publisher, Subscriber, direct_callback, payload_bytes
from followbus.bus.schemas import Frame, decode
from followbus.bus.session import ZenohSettings, open_session

from .conftest import wait_until

pytestmark = pytest.mark.skipif(shmlane.HOST_ID is None, reason="no sealable memfd on this kernel")

N = 300_000


def _segment_path(desc: list) -> str:
    """Where an attacker of the same user reaches the segment a descriptor names."""
    if len(desc) == 6:  # [pid, fd, inode, generation, length, host id]: a memfd, through /proc
        return f"/proc/{desc[0]}/fd/{desc[1]}"
    return os.path.join("/dev/shm", desc[0])  # the old named segment files


@pytest.fixture
def writer():
    session = open_session(ZenohSettings(listen=[], connect=[]))
    lane = shmlane.LaneWriter(session, "x/attack")
    yield lane
    lane.close()
    session.close()


def test_next_segment_names_squatted_or_stale_with_this_pid_change_nothing(writer):
    """Files planted under the names the lane would pick next (a squatter, or stale segments of an earlier
    process that had this pid) made the writer's O_EXCL create raise FileExistsError out of Publisher.put. Now
    nothing is created under /dev/shm at all."""
    planted = [f"/dev/shm/followbus-{shmlane.HOST_ID}-{os.getpid()}-{n}" for n in range(4000)]
    for path in planted:
        with contextlib.suppress(FileExistsError):
            os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
    try:
        for value in range(3):
            desc = msgpack.unpackb(writer.write([np.full(N, value, np.uint8)], N))
            assert (np.frombuffer(shmlane.open_blob_area(desc), np.uint8) == value).all()
        mine = [n for n in os.listdir("/dev/shm") if n.startswith("followbus-") and f"-{os.getpid()}-" in n]
        assert len(mine) == len(planted), "the lane creates nothing in /dev/shm"
    finally:
        for path in planted:
            with contextlib.suppress(OSError):
                os.unlink(path)


TRUNCATE = """
import os, sys, msgpack, numpy as np
from followbus.bus import shmlane
from followbus.bus.session import ZenohSettings, open_session
from tests.test_lane_attacks import _segment_path
s = open_session(ZenohSettings(listen=[], connect=[]))
w = shmlane.LaneWriter(s, "x/truncate")
desc = msgpack.unpackb(w.write([np.full(300_000, 3, np.uint8)], 300_000))
area = np.frombuffer(shmlane.open_blob_area(desc), np.uint8)
try:
    os.truncate(_segment_path(desc), 0)
    print("truncated", flush=True)
except OSError as exc:
    print("refused", exc.errno, flush=True)
print("sum", int(area.astype(np.int64).sum()), flush=True)  # a truncated mapping: SIGBUS here
"""


def test_truncating_a_segment_under_its_readers_is_refused():
    """`os.truncate(segment, 0)` killed every process mapping it with SIGBUS (capture, detection, template)."""
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    result = subprocess.run([sys.executable, "-c", TRUNCATE], capture_output=True, text=True, timeout=60, cwd=repo)
    assert result.returncode == 0, (result.returncode, result.stdout, result.stderr[-2000:])
    assert "refused 1" in result.stdout and f"sum {3 * N}" in result.stdout, result.stdout


def test_rewriting_a_segment_after_the_store_is_refused(writer):
    """Rolling each frame sideways after the writer's store moved the tracked centre 200 px with no error."""
    desc = msgpack.unpackb(writer.write([np.full(N, 7, np.uint8)], N))
    area = np.frombuffer(shmlane.open_blob_area(desc), np.uint8)
    fd = os.open(_segment_path(desc), os.O_RDWR)
    try:
        with pytest.raises(PermissionError):
            os.pwrite(fd, b"\x00" * 4096, shmlane.DATA_OFFSET)
        with pytest.raises(PermissionError):
            mmap.mmap(fd, shmlane.DATA_OFFSET + N, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
    finally:
        os.close(fd)
    assert (area == 7).all()


def _memfd(seals: int | None, data: bytes) -> int:
    fd = os.memfd_create(shmlane.MEMFD_NAME, os.MFD_ALLOW_SEALING)
    os.write(fd, data)
    if seals is not None:
        import fcntl

        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, seals)
    return fd


def test_forged_descriptors_are_refused(writer, tmp_path):
    """A descriptor is untrusted input: a segment without the seals (someone could still write or shrink it),
    a file that is not a followbus memfd, wrong inode, generation or length, gone, garbage."""
    real = msgpack.unpackb(writer.write([np.zeros(N, np.uint8)], N))
    pid, fd, ino, gen, length, _ = real
    header = shmlane._SEG_HEADER.pack(shmlane.SEGMENT_MAGIC, 5, 100).ljust(shmlane.DATA_OFFSET + 100, b"\0")
    unsealed = _memfd(None, header)
    half = _memfd(shmlane.SEALS & ~shmlane.F_SEAL_FUTURE_WRITE, header)
    plain = os.open(tmp_path / "plain", os.O_RDWR | os.O_CREAT)
    os.write(plain, header)
    me, host = os.getpid(), shmlane.HOST_ID
    try:
        for desc in ([me, unsealed, os.fstat(unsealed).st_ino, 5, 100, host],
                     [me, half, os.fstat(half).st_ino, 5, 100, host], [me, plain, os.fstat(plain).st_ino, 5, 100, host],
                     [pid, fd, ino, gen, length * 4, host], [pid, fd, ino, gen, 1 << 40, host],
                     [pid, fd, ino, -1, length, host], [pid, fd, ino, gen, host], [0, fd, ino, gen, 1, host],
                     [pid, fd, "1", gen, length, host], [pid, fd, ino, gen, length, "0123456789abcdef"],
                     [pid, fd, ino, gen, length, None], [pid, fd, ino, gen, length], "not a list"):
            with pytest.raises(shmlane.DecodeError) as exc:
                shmlane.open_blob_area(desc)
            assert not isinstance(exc.value, shmlane.LaneStale), desc
        for desc in ([pid, fd, ino + 1, gen, length, host], [pid, fd, ino, gen + 1, length, host],
                     [pid, 99_999, 1, 1, 1, host]):
            with pytest.raises(shmlane.LaneStale):
                shmlane.open_blob_area(desc)
        assert np.frombuffer(shmlane.open_blob_area(real), np.uint8).size == N  # the real one still reads
    finally:
        for f in (unsealed, half, plain):
            os.close(f)


class _OpenWatch:
    """inotify's IN_OPEN on some files: whether anyone opened them (through /proc/<pid>/fd/<n> too), which is
    what a descriptor must never make a reader do to a file that is not a lane segment."""

    IN_OPEN = 0x20
    _EVENT = struct.Struct("iIII")  # wd, mask, cookie, length of the name that follows

    def __init__(self, paths: list[str]):
        self._libc = ctypes.CDLL(None, use_errno=True)
        self.fd = self._libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        assert self.fd >= 0, os.strerror(ctypes.get_errno())
        for path in paths:
            assert self._libc.inotify_add_watch(self.fd, os.fsencode(path), self.IN_OPEN) >= 0, path

    def opens(self) -> int:
        try:
            data = os.read(self.fd, 65536)
        except BlockingIOError:
            return 0
        count, at = 0, 0
        while at < len(data):
            _, mask, _, length = self._EVENT.unpack_from(data, at)
            count += bool(mask & self.IN_OPEN)
            at += self._EVENT.size + length
        return count

    def close(self) -> None:
        os.close(self.fd)


def _naming(real: list, pid: int, fd: int) -> list:
    """A real descriptor made to name another process's fd (the attacker's edit: pid, fd and its inode)."""
    forged = list(real)
    forged[0], forged[1], forged[2] = pid, fd, os.stat(f"/proc/{pid}/fd/{fd}").st_ino
    return forged


def test_a_descriptor_naming_a_fifo_or_a_device_is_refused_before_any_open(writer, tmp_path):
    """Anyone who can reach the bus can publish a descriptor, and it names any process's fd: readers opened
    /proc/<pid>/fd/<n> first and checked what it was afterwards, so a descriptor naming the motor's serial port
    made them open it (an open that can reset the MCU), one naming a FIFO opened the FIFO. Now the descriptor and
    what /proc says of the fd are checked before any open: a FIFO, a terminal device (as a serial port is) and a
    device node are refused, and none of them sees an open."""
    real = msgpack.unpackb(writer.write([np.zeros(N, np.uint8)], N))
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    held = {"fifo": os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)}
    paths = {"fifo": str(fifo)}
    try:
        primary, held["tty"] = os.openpty()
        held["pty primary"] = primary
        paths["tty"] = os.ttyname(held["tty"])
    except OSError:  # no /dev/pts here: the FIFO and the device node still run
        pass
    with contextlib.suppress(OSError):  # a device node of our own needs CAP_MKNOD (root)
        os.mknod(tmp_path / "ttyFAKE0", stat.S_IFCHR | 0o600, os.makedev(1, 3))
        held["device node"] = os.open(tmp_path / "ttyFAKE0", os.O_RDONLY)
        paths["device node"] = str(tmp_path / "ttyFAKE0")
    watch = _OpenWatch(list(paths.values()))
    try:
        for name in paths:
            with pytest.raises(shmlane.DecodeError, match="not a followbus memfd") as exc:
                shmlane.open_blob_area(_naming(real, os.getpid(), held[name]))
            assert not isinstance(exc.value, shmlane.LaneStale), name
        assert watch.opens() == 0, f"a reader opened one of {sorted(paths)}"
        assert np.frombuffer(shmlane.open_blob_area(real), np.uint8).size == N  # the real one still reads
    finally:
        watch.close()
        for fd in held.values():
            os.close(fd)


OTHER_USERS_SEGMENT = """
import ctypes, fcntl, os, struct, sys, time
os.setgroups([]); os.setgid(65534); os.setuid(65534)  # nobody, and ptrace-readable as any process it starts would be
ctypes.CDLL(None).prctl(4, 1, 0, 0, 0)  # PR_SET_DUMPABLE: a changed uid clears it
fd = os.memfd_create("followbus-lane", os.MFD_ALLOW_SEALING)
os.write(fd, struct.pack("<8sQQ", b"FBLANE01", 5, 100).ljust(64 + 100, b"\\0"))
fcntl.fcntl(fd, 1033, int(sys.argv[1]))
print(fd, flush=True)
time.sleep(60)
"""


@pytest.mark.skipif(os.geteuid() != 0, reason="running a process as another user needs root")
def test_a_segment_of_another_users_process_is_refused_before_any_open(writer):
    """A descriptor published by another user (here `nobody`) naming a followbus-lane memfd of its own, sealed
    as ours are: a reader running as root opened it (root may open any /proc/<pid>/fd) before seeing whose it
    was. Now the named process must be this user's before anything is opened."""
    real = msgpack.unpackb(writer.write([np.zeros(N, np.uint8)], N))
    other = subprocess.Popen([sys.executable, "-c", OTHER_USERS_SEGMENT, str(shmlane.SEALS)], stdout=subprocess.PIPE,
                             text=True)
    try:
        fd = int(other.stdout.readline())
        forged = _naming(real, other.pid, fd)
        forged[3], forged[4] = 5, 100
        watch = _OpenWatch([f"/proc/{other.pid}/fd/{fd}"])
        try:
            with pytest.raises(shmlane.DecodeError) as exc:
                shmlane.open_blob_area(forged)
            assert watch.opens() == 0, "the reader opened another user's file"
            assert "process" in str(exc.value) and "not this user's" in str(exc.value)
        finally:
            watch.close()
    finally:
        other.kill()
        other.wait()


def test_a_flood_of_lane_tokens_is_bounded_and_sends_inline():
    session = open_session(ZenohSettings(listen=[], connect=[]))
    writer = shmlane.LaneWriter(session, "x/attack")
    try:
        tokens = [shmlane.declare_token(session, "x/attack") for _ in range(shmlane.MAX_TRACKED_TOKENS + 50)]
        assert wait_until(lambda: writer.overflowed, 10)
        assert len(writer._tokens) <= shmlane.MAX_TRACKED_TOKENS and not writer.ready
        for token in tokens:
            token.undeclare()
    finally:
        writer.close()
        session.close()


H, W = 480, 640


def _frame(value: int, seq: int) -> Frame:
    msg = Frame(width=W, height=H, encoding="bgr8", data=np.full((H, W, 3), value, np.uint8))
    msg.header.frame_seq = seq
    return msg


@pytest.mark.slow
@pytest.mark.parametrize("remote", [False, True])
def test_a_plain_zenoh_subscriber_gets_real_frames_while_the_lane_serves_followbus(port, remote):
    """A raw zenoh-python subscriber (no token) shares the key with a followbus lane subscriber: it receives the
    real encoded frames (on main it got ~400 B descriptors), while the followbus one gets lane views, or
    inline copies when a subscriber of another host is announced (``remote``)."""
    a = open_session(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    raw_session = open_session(ZenohSettings(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    b = open_session(ZenohSettings(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    lane_views: list[bool] = []
    raw: list[bytes] = []
    sub = Subscriber(a, "lane/raw", lambda m: m.header.frame_seq >= 0 and lane_views.append(
        isinstance(m.data.base, np.ndarray) or not (m.data == m.header.frame_seq).all()), schema=Frame, lane=True)
    other = (a.liveliness().declare_token(f"{shmlane.TOKEN_PREFIX}/0123456789abcdef/{'ab' * 8}/{b'lane/**'.hex()}")
             if remote else None)
    plain = raw_session.declare_subscriber("lane/raw", direct_callback(lambda s: raw.append(payload_bytes(s))))
    pub = Publisher(b, "lane/raw", "rawtest", lane=True)
    try:
        assert wait_until(lambda: pub.put(_frame(255, -1)) and pub._lane is not None
                          and (pub._lane.ready or remote) and raw and lane_views is not None, 10, interval=0.05)
        time.sleep(0.3)
        raw.clear()
        lane_views.clear()
        for i in range(5):
            pub.put(_frame(i, i))
            time.sleep(0.03)
        assert wait_until(lambda: len(raw) >= 5 and len(lane_views) >= 5, 10), (len(raw), lane_views)
        assert all(data[:3] == MAGIC for data in raw), {data[:3] for data in raw}
        decoded = [decode(data, Frame) for data in raw]
        assert [m.header.frame_seq for m in decoded] == list(range(5))
        assert all((m.data == m.header.frame_seq).all() for m in decoded)
        assert pub._lane.ready is not remote
        assert len(lane_views) == 5 and sub.stats.decode_errors == 0
    finally:
        if other is not None:
            other.undeclare()
        pub.undeclare()
        plain.undeclare()
        sub.undeclare()
        for s in (b, raw_session, a):
            s.close()
