"""The commands that produce the numbers of BENCHMARKS.md, EVALUATION.md and RELIABILITY.md:
``followbus bench pipeline``, ``followbus chaos`` and ``followbus eval``."""
