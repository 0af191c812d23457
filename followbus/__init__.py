"""followbus: a person-following robot's perception-and-control graph over Eclipse Zenoh."""

from importlib.metadata import version as _version

__version__ = _version("followbus")  # pyproject's, the one place it is written
