"""Errors every command reports the same way: one line on stderr, exit status 2 (tools/cli.py main)."""

from __future__ import annotations


class UsageError(Exception):
    """A mistake on the command line or in what it names (a --set, a missing password); the message is the
    whole line: what is wrong and what to do."""
