"""A full /dev/shm (something else filled it) must not crash-loop every node at start: `zenoh.open` raised
"Unable to create POSIX shm segment" and nothing retried without shared memory; one failed allocation turned
Zenoh's shared memory off for the rest of the process (ShmPool._failed). Run in a private mount namespace with a
tiny tmpfs on /dev/shm, so the machine's real /dev/shm is never filled."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from .conftest import REPO

SCRIPT = """
import os, sys, time
from followbus.bus import pubsub
from followbus.bus.session import ZenohSettings, open_session
with open("/dev/shm/filler", "wb") as f:
    try:
        while True:
            f.write(b"\\0" * 65536)
    except OSError:
        pass
try:
    s = open_session(ZenohSettings(listen=[], connect=[], shm=True))
except Exception as exc:
    print("session failed:", exc, flush=True)
    sys.exit(3)
pubsub.SHM_RETRY_S = 0.2
pool = pubsub.ShmPool(1024 * 1024)
print("alloc while full:", pool.buffer_with(b"x" * 100_000) is not None, flush=True)
os.unlink("/dev/shm/filler")
time.sleep(0.3)
print("alloc once freed:", pool.buffer_with(b"x" * 100_000) is not None, flush=True)
s.close()
"""


def _private_shm(command: list[str]) -> list[str]:
    return ["unshare", "-m", "sh", "-c", 'mount --make-rprivate / && mount -t tmpfs -o size=8m tmpfs /dev/shm && '
            'exec "$@"', "sh", *command]


def test_a_full_dev_shm_opens_the_session_without_shm_and_allocation_is_retried():
    if shutil.which("unshare") is None or subprocess.run(_private_shm(["true"]), capture_output=True).returncode:
        pytest.skip("no private mount namespace here (unshare -m and mount need CAP_SYS_ADMIN)")
    result = subprocess.run(_private_shm([sys.executable, "-c", SCRIPT]), capture_output=True, text=True,
                            timeout=60, cwd=REPO)
    out = result.stdout + result.stderr
    assert result.returncode == 0, out[-3000:]
    assert "opening the session without it" in out
    assert "alloc while full: False" in out and "alloc once freed: True" in out, out[-3000:]
