"""Pure evaluation: datasets, metrics, baselines (no bus imports).

"Seed NNN" names a method paper (glossary: tracking/__init__.py).
"""
