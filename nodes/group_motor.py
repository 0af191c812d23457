"""group_motor: motor following a group's centre instead of a person's track (see nodes/motor.py GroupMotor)."""

from .motor import GroupMotor

NODE = GroupMotor
