"""Replaying recordings into nodes: the plan, the feed, the engines and the diff (``followbus replay``)."""
