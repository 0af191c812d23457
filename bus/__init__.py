"""Thin layer over Zenoh: sessions, schemas, codec, pub/sub, sync, health, stats. Knows nothing of tracking."""
