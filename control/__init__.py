"""Pure motion control: PID, width-based range, Mecanum kinematics, drivers (no bus imports)."""
