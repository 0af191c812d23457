"""Relay node (see followbus.nodes.diagnostics)."""

from .diagnostics import Relay

NODE = Relay
