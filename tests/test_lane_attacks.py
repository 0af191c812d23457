"""The same-host lane against a local process (issue 25 item 2, issue 23 item 2): segments whose names could be
squatted or left stale with a reused pid, truncated under their readers (SIGBUS), or rewritten after the store;
forged descriptors; and a plain Zenoh subscriber that declares no token must get real frames, not descriptors."""

from __future__ import annotations

import contextlib
import mmap
import os
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
    if len(desc) == 5:  # [pid, fd, inode, generation, length]: a memfd, through /proc
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
    pid, fd, ino, gen, length = real
    header = shmlane._SEG_HEADER.pack(shmlane.SEGMENT_MAGIC, 5, 100).ljust(shmlane.DATA_OFFSET + 100, b"\0")
    unsealed = _memfd(None, header)
    half = _memfd(shmlane.SEALS & ~shmlane.F_SEAL_FUTURE_WRITE, header)
    plain = os.open(tmp_path / "plain", os.O_RDWR | os.O_CREAT)
    os.write(plain, header)
    me = os.getpid()
    try:
        for desc in ([me, unsealed, os.fstat(unsealed).st_ino, 5, 100], [me, half, os.fstat(half).st_ino, 5, 100],
                     [me, plain, os.fstat(plain).st_ino, 5, 100], [pid, fd, ino, gen, length * 4],
                     [pid, fd, ino, gen, 1 << 40], [pid, fd, ino, -1, length], [pid, fd, ino, gen],
                     [0, fd, ino, gen, 1], [pid, fd, "1", gen, length], "not a list"):
            with pytest.raises(shmlane.DecodeError) as exc:
                shmlane.open_blob_area(desc)
            assert not isinstance(exc.value, shmlane.LaneStale), desc
        for desc in ([pid, fd, ino + 1, gen, length], [pid, fd, ino, gen + 1, length], [pid, 99_999, 1, 1, 1]):
            with pytest.raises(shmlane.LaneStale):
                shmlane.open_blob_area(desc)
        assert np.frombuffer(shmlane.open_blob_area(real), np.uint8).size == N  # the real one still reads
    finally:
        for f in (unsealed, half, plain):
            os.close(f)


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
