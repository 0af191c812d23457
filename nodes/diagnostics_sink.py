"""Sink node (see followbus.nodes.diagnostics)."""

from .diagnostics import Sink

NODE = Sink
