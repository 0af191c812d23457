"""``followbus play``: publish a recording's bus messages (their stored bytes) on their keys, or on
remapped ones, paced by log time (the bus stamps) times ``--rate``, or as fast as the bus takes them.

In a terminal: space pauses/resumes, ``s`` publishes one message while paused, ``q`` quits.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import select
import signal
import sys
import threading
import time
from pathlib import Path

import zenoh

from ...bus.pubsub import Publisher, ShmPool
from ...bus.recording import RecordingError, bus_channels, chunks_to_skip, iter_bus_messages
from .record import is_status_key

log = logging.getLogger("followbus.play")


def parse_remaps(items: list[str]) -> list[tuple[str, str]]:
    out = []
    for item in items:
        src, sep, dst = item.partition("=")
        if not sep or not src or not dst:
            raise ValueError(f"remap {item!r} must look like from=to (key prefixes, e.g. fb=fb2)")
        out.append((src.rstrip("/"), dst.rstrip("/")))
    return out


def remap_key(key: str, remaps: list[tuple[str, str]]) -> str:
    """The first matching ``from=to`` wins; ``from`` matches the whole key or a prefix up to a '/'."""
    for src, dst in remaps:
        if key == src:
            return dst
        if key.startswith(src + "/"):
            return dst + key[len(src):]
    return key


def select_keys(keys: list[str], patterns: list[str] | None, include_status: bool) -> list[str]:
    exprs = [zenoh.KeyExpr(p) for p in patterns or []]
    chosen = []
    for key in keys:
        if not include_status and is_status_key(key):
            continue
        if exprs and not any(e.intersects(zenoh.KeyExpr(key)) for e in exprs):
            continue
        chosen.append(key)
    return sorted(chosen)


class Keyboard:
    """Single key presses from a terminal (cbreak mode, restored on close)."""

    def __init__(self) -> None:
        import termios
        import tty

        self._fd = sys.stdin.fileno()
        self._saved = termios.tcgetattr(self._fd)
        tty.setcbreak(self._fd)
        self.keys: queue.SimpleQueue[str] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="keyboard", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._fd], [], [], 0.1)
            if ready:
                ch = sys.stdin.read(1)
                if ch:
                    self.keys.put(ch)

    def close(self) -> None:
        import termios

        self._stop.set()
        self._thread.join(timeout=1.0)
        termios.tcsetattr(self._fd, termios.TCSADRAIN, self._saved)


class Player:
    skip_chunks: frozenset[int] = frozenset()  # corrupt chunks the user chose to skip (--on-corrupt skip)

    def __init__(self, session: zenoh.Session, path: Path, keys: list[str], remaps: list[tuple[str, str]], *,
                 rate: float | None, loop: bool, paused: bool, shm: bool, keyboard: Keyboard | None = None):
        self.path = path
        self.keys = keys
        self.rate = rate  # None: as fast as possible
        self.loop = loop
        self.paused = paused
        self.keyboard = keyboard
        self.stop_event = threading.Event()
        pool = ShmPool() if shm else None
        # Declared up front so the first messages do not race the publishers' declarations.
        self.publishers = {key: Publisher(session, remap_key(key, remaps), "play", shm=pool) for key in keys}
        self.published = 0
        self._step = False

    def _handle_keys(self) -> None:
        if self.keyboard is None:
            return
        while True:
            try:
                ch = self.keyboard.keys.get_nowait()
            except queue.Empty:
                return
            if ch == " ":
                self.paused = not self.paused
                print("paused" if self.paused else "playing", file=sys.stderr, flush=True)
            elif ch == "s" and self.paused:
                self._step = True
            elif ch in ("q", "\x03"):
                self.stop_event.set()

    def _wait_turn(self, target_wall: float | None) -> bool:
        """Block until this message may go out; True if the time base must be re-anchored (pause/step)."""
        reanchor = False
        while not self.stop_event.is_set():
            self._handle_keys()
            if self.paused:
                reanchor = True
                if self._step:
                    self._step = False
                    return True
                time.sleep(0.02)
                continue
            if reanchor or target_wall is None:
                return reanchor
            remaining = target_wall - time.monotonic()
            if remaining <= 0:
                return False
            time.sleep(min(remaining, 0.02))
        return reanchor

    def run(self) -> int:
        while not self.stop_event.is_set():
            anchor_wall: float | None = None
            anchor_log = 0
            for msg in iter_bus_messages(self.path, self.keys, self.skip_chunks):
                if anchor_wall is None:
                    anchor_wall, anchor_log = time.monotonic(), msg.log_time
                target = None if self.rate is None else anchor_wall + (msg.log_time - anchor_log) / 1e9 / self.rate
                if self._wait_turn(target):
                    anchor_wall, anchor_log = time.monotonic(), msg.log_time  # resume from here, not catch up
                if self.stop_event.is_set():
                    break
                self.publishers[msg.key].put_bytes(msg.data, msg.log_time)
                self.published += 1
            if not self.loop:
                break
        return self.published


def _join(settings) -> zenoh.Session | None:
    """A session whose messages the graph accepts, or None after one line saying why not (access control).
    A graph that cannot be joined at all raises BusUnreachable (one line, exit 2, from the command line)."""
    from ..connect import PublishRefused, auth_user, check_can_publish, open_client_session

    session = open_client_session(settings)
    try:
        check_can_publish(session, settings)
    except PublishRefused as exc:
        session.close()
        print(f"followbus: play refused: {exc}", file=sys.stderr)
        return None
    user = auth_user(settings.config)
    print(f"joined {', '.join(settings.connect)}{f' as {user}' if user else ''}: the graph accepts our messages",
          flush=True)
    return session


def cmd_play(args, settings) -> int:
    path = Path(args.file)
    try:
        remaps = parse_remaps(args.remap or [])
        keys = select_keys(list(bus_channels(path)), args.topics, args.status)
        # Before anything is published: a corrupt chunk is refused (or skipped, named) now, not half-way.
        skip = chunks_to_skip(path, keys, args.on_corrupt)
    except (RecordingError, ValueError) as exc:
        print(f"followbus: {exc}", file=sys.stderr)
        return 2
    if not keys:
        print(f"followbus: {path}: no bus channel matches", file=sys.stderr)
        return 2
    rate = None if args.fast else args.rate
    if args.start_paused and not sys.stdin.isatty():
        print("followbus: --start-paused needs a terminal (space resumes)", file=sys.stderr)
        return 2
    session = _join(settings)
    if session is None:
        return 2
    keyboard = Keyboard() if sys.stdin.isatty() else None
    player = Player(session, path, keys, remaps, rate=rate, loop=args.loop, paused=args.start_paused,
                    shm=settings.shm, keyboard=keyboard)
    player.skip_chunks = skip

    def on_signal(signum, _frame):
        if signum == signal.SIGINT:
            from ..errors import INTERRUPTED

            INTERRUPTED.set()  # exit 130, once the player has stopped cleanly
        player.stop_event.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    started = time.monotonic()
    print(f"playing {len(keys)} keys from {path} at "
          f"{'full speed' if rate is None else f'{rate:g}x'}"
          + ("; paused (space: play, s: step, q: quit)" if args.start_paused else "")
          + ("; space: pause, s: step, q: quit" if keyboard and not args.start_paused else ""), flush=True)
    try:
        published = player.run()
    finally:
        if keyboard is not None:
            keyboard.close()
        for pub in player.publishers.values():
            with contextlib.suppress(Exception):
                pub.undeclare()
        with contextlib.suppress(Exception):
            session.close()
    print(f"published {published} messages in {time.monotonic() - started:.1f} s", flush=True)
    return 0
