"""Pure vision: detectors, model search path, synthetic scenes, frame sources (no bus imports).

"Seed NNN" names a method paper (glossary: tracking/__init__.py).
"""
