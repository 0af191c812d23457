"""What the viewers of a running graph share: the monitor's state from the bus (monitor.py), the views of
its messages that make its snapshot (snapshot.py) and the shapes they draw (drawing.py).

"Seed NNN" names a method paper (glossary: tracking/__init__.py).
"""
