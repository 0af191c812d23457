"""The reliability bench (``followbus bench chaos``): the runner that launches the graph and injects faults
(chaos.py), the fault catalogue (faults.py), and the judging of what the loop did (judging.py)."""
