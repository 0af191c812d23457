"""followbus: a person-following robot's perception-and-control graph over Eclipse Zenoh."""

__version__ = "0.1.0"
