"""MCAP recordings of the bus: ``followbus record``, ``play``, ``replay``, ``info`` and ``recover``, and the
Foxglove views a recording carries. Reading a recording is bus/recording.py's (nodes read them too)."""
