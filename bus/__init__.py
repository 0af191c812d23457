"""Thin layer over Zenoh: sessions, schemas, codec, pub/sub, sync, health, stats.

Generic: it carries any message type; the application's own are in msgs/."""
