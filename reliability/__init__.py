"""The reliability bench (``followbus bench chaos``): the fault catalogue and the runner that injects them into
a launched graph (chaos.py), and the judging of what the loop did (judging.py)."""
