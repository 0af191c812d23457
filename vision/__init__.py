"""Pure vision: detectors, model search path, synthetic scenes, frame sources (no bus imports)."""
