"""Two machines on one: two Linux network namespaces joined by a veth pair, optionally shaped (htb rate), and
processes started in either with a /dev/shm of their own, as a second computer has.

Used by ``followbus bench link`` (a laptop on a slow link) and the two-host tests. Needs root (``ip netns``);
:func:`netns_unavailable` says why not, for a test to skip with. Everything is removed on exit: deleting a
namespace deletes its end of the veth pair, and the other end with it.

``ip netns exec`` gives the process the namespace's network; ``unshare -m`` a private mount namespace in which
a fresh tmpfs is mounted on /dev/shm. A different /dev/shm is a different host to the same-host lane
(bus/shmlane.py hashes /dev/shm's device into its host id), so frames cross between the two inline.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
from dataclasses import dataclass

PREFIX_ENV = "FOLLOWBUS_NETNS_PREFIX"  # namespace/interface name prefix (default fbt<pid>)
SUBNET_ENV = "FOLLOWBUS_NETNS_SUBNET"  # first three octets of the pair's addresses (default 10.200.<pid % 250>)
SHM_SIZE = "512m"


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20, check=check)


def netns_unavailable() -> str | None:
    """Why two network namespaces cannot be made here (None: they can)."""
    if os.geteuid() != 0:
        return "needs root for ip netns"
    missing = [tool for tool in ("ip", "tc", "unshare") if shutil.which(tool) is None]
    if missing:
        return f"{', '.join(missing)} not installed"
    probe = f"fbprobe{os.getpid()}"
    made = _ip("netns", "add", probe, check=False)
    if made.returncode != 0:
        return f"ip netns add is not permitted here: {made.stderr.strip()}"
    _ip("netns", "del", probe, check=False)
    return None


@dataclass
class NetnsPair:
    """Namespaces ``<prefix>-a`` (address ``<subnet>.1``) and ``<prefix>-b`` (``<subnet>.2``) on a veth pair
    whose both ends are limited to ``rate_mbit`` (None: unshaped). A context manager."""

    prefix: str = ""
    subnet: str = ""
    rate_mbit: float | None = None

    def __post_init__(self) -> None:
        self.prefix = self.prefix or os.environ.get(PREFIX_ENV) or f"fbt{os.getpid() % 100000}"
        self.subnet = self.subnet or os.environ.get(SUBNET_ENV) or f"10.200.{os.getpid() % 250}"
        self.names = (f"{self.prefix}-a", f"{self.prefix}-b")
        self.links = (f"{self.prefix}a"[:15], f"{self.prefix}b"[:15])
        self.addresses = (f"{self.subnet}.1", f"{self.subnet}.2")

    def __enter__(self) -> NetnsPair:
        self.down()  # a previous run killed before its clean-up
        try:
            self._up()
        except Exception:
            self.down()
            raise
        return self

    def __exit__(self, *_exc) -> None:
        self.down()

    def _up(self) -> None:
        for name in self.names:
            _ip("netns", "add", name)
        _ip("link", "add", self.links[0], "type", "veth", "peer", "name", self.links[1])
        for name, link, address in zip(self.names, self.links, self.addresses, strict=True):
            _ip("link", "set", link, "netns", name)
            _ip("-n", name, "addr", "add", f"{address}/24", "dev", link)
            _ip("-n", name, "link", "set", link, "up")
            _ip("-n", name, "link", "set", "lo", "up")
            if self.rate_mbit:
                self._shape(name, link)

    def _shape(self, name: str, link: str) -> None:
        """htb on the egress of this end (netem is not in every kernel; htb is): each direction is capped."""
        rate = f"{self.rate_mbit:g}mbit"
        for args in (["qdisc", "add", "dev", link, "root", "handle", "1:", "htb", "default", "10"],
                     ["class", "add", "dev", link, "parent", "1:", "classid", "1:10", "htb", "rate", rate,
                      "ceil", rate]):
            subprocess.run(["ip", "netns", "exec", name, "tc", *args], capture_output=True, text=True, timeout=20,
                           check=True)

    def down(self) -> None:
        for name in self.names:
            _ip("netns", "del", name, check=False)
        with contextlib.suppress(Exception):
            _ip("link", "del", self.links[0], check=False)

    def argv(self, side: int, command: list[str], private_shm: bool = True) -> list[str]:
        """``command`` run in namespace ``side`` (0: a, 1: b), with its own /dev/shm unless told otherwise."""
        head = ["ip", "netns", "exec", self.names[side]]
        if not private_shm:
            return [*head, *command]
        mount = f'mount -t tmpfs -o size={SHM_SIZE},mode=1777 tmpfs /dev/shm && exec "$@"'
        return [*head, "unshare", "-m", "--propagation", "private", "sh", "-c", mount, "sh", *command]
