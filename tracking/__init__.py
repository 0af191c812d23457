"""Pure target-tracking algorithms of seed 000 (no bus imports)."""
