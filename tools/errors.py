"""Errors every command reports the same way: one line on stderr, exit status 2 (tools/cli.py main)."""

from __future__ import annotations

import threading

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
