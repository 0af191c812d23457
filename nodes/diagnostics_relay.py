"""Relay node (see followbus.nodes.diagnostics)."""

from followbus.nodes.diagnostics import Relay

NODE = Relay
