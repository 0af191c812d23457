"""Pure motion control: PID, width-based range, Mecanum kinematics, drivers (no bus imports).

"Seed NNN" names a method paper (glossary: tracking/__init__.py).
"""
