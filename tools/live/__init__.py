"""Watching a running graph, read-only: ``followbus monitor`` (terminal and web view), ``foxglove``, and the
introspection commands ``topics``, ``echo``, ``hz``, ``nodes`` and ``router``."""
