"""Pure evaluation: datasets, metrics, baselines (no bus imports)."""
