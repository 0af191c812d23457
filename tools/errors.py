"""Errors every command reports the same way: one line on stderr, exit status 2 (tools/cli.py main)."""

from __future__ import annotations

import threading

# Ctrl-C (SIGINT) arrived: the command exits with status 130 however it then stopped (tools/cli.py main), whether
# the default handler raised KeyboardInterrupt or a command's own handler stopped it gently (launch, demo).
INTERRUPTED = threading.Event()


class UsageError(Exception):
    """A mistake on the command line or in what it names (a --set, a missing password); the message is the
    whole line: what is wrong and what to do."""
