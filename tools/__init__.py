"""The followbus command line.

"Seed NNN" names a method paper (glossary: tracking/__init__.py).
"""

from importlib.metadata import version as _version

# One version, pyproject's: tools/ cannot import followbus/__init__.py by path (package-dir maps it apart).
__version__ = _version("followbus")
