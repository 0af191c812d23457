"""Sink node (see followbus.nodes.diagnostics)."""

from followbus.nodes.diagnostics import Sink

NODE = Sink
