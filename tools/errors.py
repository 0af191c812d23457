"""Errors every command reports the same way: one line on stderr, exit status 2 (tools/cli.py main)."""

from __future__ import annotations

import os
import tempfile
import threading
from pathlib import Path

# Ctrl-C (SIGINT) arrived: the command exits with status 130 however it then stopped (tools/cli.py main), whether
# the default handler raised KeyboardInterrupt or a command's own handler stopped it gently (launch, demo).
INTERRUPTED = threading.Event()


class UsageError(Exception):
    """A mistake on the command line or in what it names (a --set, a missing password); the message is the
    whole line: what is wrong and what to do."""


def write_text_output(text: str, output: str | None, what: str = "") -> int:
    """A command's text to ``--output`` (saying so, with ``what`` it holds), or to stdout without one; a path that
    cannot be written is a UsageError (one line, exit 2)."""
    import sys
    from pathlib import Path

    if not output:
        sys.stdout.write(text)
        return 0
    try:
        Path(output).write_text(text)
    except OSError as exc:
        raise UsageError(f"cannot write {output}: {exc.strerror}") from exc
    print(f"wrote {output}{f' ({what})' if what else ''}")
    return 0


def _cannot_write_in(directory: Path, create: bool = True) -> str | None:
    """Why this process cannot make files in ``directory`` (created with its parents if missing, or with ``create``
    False only looked at: the nearest directory that exists is tried), or None."""
    if create:
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            return f"cannot create {directory}: {exc.strerror}"
    existing = directory
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is not a directory"
    try:  # a file made and removed: permission bits do not bind root, and /proc or a read-only mount refuse anyway
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as exc:
        return f"cannot write in {existing}: {exc.strerror}"
    return None


def writable_directory(path: str | os.PathLike, option: str) -> Path:
    """``path`` as a directory this process can write in, created with its parents if missing; a UsageError naming
    ``option`` when it cannot be (checked before anything starts: a launch's node logs or an evaluation's results
    must not fail later, in a thread, with a traceback)."""
    directory = Path(path)
    problem = _cannot_write_in(directory)
    if problem:
        raise UsageError(f"{option} {path}: {problem}")
    return directory


def output_file_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be written as a file (nothing is created to find out), or None."""
    target = Path(path)
    if target.is_dir():
        return "is a directory (give a file name)"
    return _cannot_write_in(target.parent, create=False)
